"""The result first, as a lab engineer reads it (issue 50): `velab fit`, `velab info` and `velab record`
open with the headline (best model, support, a +- SE, every Kelvin-Voigt element with its SEs, the noise
ratio), the default report stays within 100 columns, the full detail comes with -v, the JSON gains a
"headline" object and keeps its keys."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from velab.cli import main
from velab.fitting.results import SweepResult
from velab.runfiles.summary import read_fits

FIT = ["--models", "2,3", "--window", "5"]


def _stored(path) -> SweepResult:
    """The one fit stored in the run file, as a SweepResult."""
    (d,) = read_fits(path).values()
    return SweepResult.from_dict(d)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A synthetic run of material A (S3), fitted once by `velab fit` (default text report, saved)."""
    import contextlib
    import io

    p = tmp_path_factory.mktemp("report") / "a.h5"
    assert main(["synth", "--material", "A", "--duration", "6", "--seed", "5", "-o", str(p)]) == 0
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["fit", str(p), *FIT]) == 0
    return p, out.getvalue()


def _first_lines_name_the_result(lines, result):
    best = result.best
    assert lines[0].startswith(f"RESULT (fit): best model {best.name}"), lines[:3]
    top = "\n".join(lines[:12])
    assert f"a = {best.wave_speed_m_s:.2f} +- {best.wave_speed_se_m_s:.2g} m/s" in top
    for el in best.elements():  # every element's E, eta, tau and J with its standard error
        assert f"{el['E']:.3e} +- {el['E_se']:.2g}" in top and f"{el['eta']:.3e} +- {el['eta_se']:.2g}" in top
        assert f"{el['tau']:.4g} +- {el['tau_se']:.2g}" in top and f"{el['J']:.3e} +- {el['J_se']:.2g}" in top
    assert "noise ratio F/noise" in top


def test_fit_opens_with_the_result_within_100_columns(fitted):
    path, text = fitted
    lines = text.splitlines()
    assert lines[0] == str(path)
    _first_lines_name_the_result(lines[1:], _stored(path))
    report = [line for line in lines if not line.startswith("run: ")]  # (a path is as long as the folder makes it)
    assert max(map(len, report)) <= 100, max(report, key=len)
    for detail in ("AIC AR1", "n_eff", "J_rel", "lag-1"):  # the detail only with -v
        assert detail not in text
    assert lines[-1].startswith("saved as /entry/fits/")


def test_info_of_a_fitted_run_opens_with_its_fits_result(fitted, capsys):
    path, _ = fitted
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    _first_lines_name_the_result(lines, _stored(path))
    assert "[fit auto_w5s]" in lines[0]


def test_verbose_fit_gives_every_statistic_and_json_gains_a_headline(fitted, capsys):
    path, _ = fitted
    capsys.readouterr()
    assert main(["-v", "fit", str(path), *FIT, "--no-save"]) == 0
    text = capsys.readouterr().out
    assert text.splitlines()[1].startswith("RESULT (fit): best model S3")
    for detail in ("AIC AR1", "n_eff", "J_rel", "lag-1", "bounds: tau in"):
        assert detail in text
    assert main(["fit", str(path), *FIT, "--no-save", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    h = doc["headline"]
    assert h["best_model"] == doc["best"] == "S3" and len(h["elements"]) == 3
    best = next(m for m in doc["models"] if m["name"] == "S3")
    assert [e["E_pa"] for e in h["elements"]] == [e["E"] for e in best["elements"]]
    assert h["wave_speed_se_m_s"] == best["wave_speed_se"] and h["noise_ratio"] == best["noise_ratio"]
    for key in ("models", "warnings", "adequacy", "creep_averaged", "notes", "settings"):  # nothing removed
        assert key in doc


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_record_report_opens_with_the_result_within_100_columns(tmp_path):
    p = subprocess.run([sys.executable, "-m", "velab.cli", "record", "--simulate", "--fast", "--duration", "6",
                        "--window", "5", "--models", "2,3", "--out-dir", str(tmp_path)],
                       capture_output=True, text=True, timeout=280)
    assert p.returncode == 0, p.stderr[-2000:]
    lines = [line for line in p.stdout.splitlines()]
    while lines and not lines[0]:
        lines.pop(0)
    path = next(line.removeprefix("run: ") for line in lines if line.startswith("run: "))
    _first_lines_name_the_result(lines, _stored(path))
    report = [line for line in lines if not line.startswith("run: ")]  # (a path is as long as the folder makes it)
    assert max(map(len, report)) <= 100, max(report, key=len)
    assert "AIC AR1" not in p.stdout and "n_eff" not in p.stdout


def test_the_live_status_line_keeps_the_peak_head_on_80_columns():
    from velab.commands.record import status_line

    worst = {"phase": "completed-with-faults", "countdown": "armed timeout 299.8 s", "t": 3599.123,
             "samples": 3_600_000, "lost": 123_456, "peak": 152.25}
    usual = {"phase": "recording", "countdown": "fit window 12.3 s", "t": 14.1, "samples": 24_000, "lost": 0,
             "peak": 52.25}
    for state in (worst, usual):
        for width in (79, 70, 60):
            line = status_line(state, width)
            assert len(line) <= width and f"{state['peak']:.2f} m" in line and state["phase"] in line, line
    assert "fit window 12.3 s" in status_line(usual, 79)  # the countdown too, on an 80-column terminal
    assert status_line(usual, 200).endswith("24000 samples, 0 lost")  # everything on a wide one
