"""Joint fits of a campaign (velab fit --joint, velab.fitting.joint; issue 25 parts 1 and 3).

Data the fitter did not make: `velab synth` (the time-domain model with the rig's real butterfly valve
on its sigmoid in position, the orifice law and quadratic friction) on the reference rig at three
steady flows, sigma 0.1 m, exported as head-only CSVs and brought back by `velab import` (so every
run's closure is fitted as nuisance parameters). Records of 8 s after the trigger keep the module at
a few tens of seconds.
"""

import hashlib
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from velab.cli import main
from velab.config import load_material, load_rig
from velab.fitting.engine import HeadEvaluator
from velab.fitting.campaignrun import head_sha256
from velab.fitting.stacked import StackedEvaluator
from velab.runfiles import read_run
from velab.fitting.report import format_report

WINDOW = 8.0
RIG = Path(__file__).resolve().parents[2] / "configs" / "rigs" / "perugia.toml"


def _rig_file(tmp: Path, q0_l_s: float, length_m: float | None = None) -> Path:
    text = RIG.read_text()
    text = text.replace("steady_flow_m3_s = 3.64e-3", f"steady_flow_m3_s = {q0_l_s / 1e3!r}")
    if length_m is not None:
        text = text.replace("length_m = 102.58", f"length_m = {length_m!r}")
    out = tmp / f"rig_{q0_l_s:g}_{length_m or 'ref'}.toml"
    out.write_text(text)
    return out


def _csv_run(tmp: Path, name: str, q0_l_s: float, material: str, seed: int, length_m: float | None = None) -> Path:
    """`velab synth` -> head-only CSV -> `velab import`: a run file whose closure the fit must find."""
    rig = _rig_file(tmp, q0_l_s, length_m)
    synth = tmp / f"synth_{name}.h5"
    assert main(["synth", "--rig", str(rig), "--material", material, "--duration", str(WINDOW), "--pretrigger", "0.6",
                 "--seed", str(seed), "-o", str(synth), "-q"]) == 0
    run = read_run(synth)
    csv = tmp / f"{name}.csv"
    with open(csv, "w") as f:
        f.write("time_s,head_m\n")
        for a, b in zip(run.time_s, run.head_m):
            f.write(f"{a:.6f},{b:.6f}\n")
    out = tmp / f"{name}.h5"
    assert main(["import", str(csv), "--rig", str(rig), "-o", str(out), "-q"]) == 0
    return out


def _file_sha(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """Three runs of material A's pipe at 2.5, 3.64 and 4.5 l/s, and one of material B's wall."""
    tmp = tmp_path_factory.mktemp("campaign")
    runs = [_csv_run(tmp, f"r{i + 1}", q, "A", seed) for i, (q, seed) in enumerate(((2.5, 21), (3.64, 22), (4.5, 23)))]
    other = _csv_run(tmp, "wall_b", 3.0, "B", 24)
    # the record of a 120 m pipe imported with the reference rig file (which says 102.58 m): a run that
    # claims to be of this pipe and is not
    rig_long = _rig_file(tmp, 3.2, 120.0)
    synth = tmp / "synth_long.h5"
    assert main(["synth", "--rig", str(rig_long), "--material", "A", "--duration", str(WINDOW), "--pretrigger", "0.6",
                 "--seed", "7", "-o", str(synth), "-q"]) == 0
    run = read_run(synth)
    csv = tmp / "long.csv"
    with open(csv, "w") as f:
        f.write("time_s,head_m\n")
        for a, b in zip(run.time_s, run.head_m):
            f.write(f"{a:.6f},{b:.6f}\n")
    long_pipe = tmp / "long_pipe.h5"
    assert main(["import", str(csv), "--rig", str(_rig_file(tmp, 3.2)), "-o", str(long_pipe), "-q"]) == 0
    return tmp, runs, (other, long_pipe)


@pytest.fixture(scope="module")
def joint(campaign):
    """`velab fit r1.h5 r2.h5 r3.h5 --joint --json --plot`: the document, saved into the runs."""
    tmp, runs, _ = campaign
    before = {p: head_sha256(read_run(p).time_s, read_run(p).head_m) for p in runs}
    figure = tmp / "campaign.png"
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["fit", *map(str, runs), "--joint", "--json", "--window", str(WINDOW), "--plot", str(figure)])
    assert code == 0
    return json.loads(out.getvalue()), before, figure


def test_three_runs_of_one_pipe_give_its_wall(joint):
    """Issue 25's acceptance: S3, a within 0.5 m/s of 353.73, no run disagreeing, every run's residual at
    its own noise."""
    doc, _, _ = joint
    best = next(m for m in doc["models"] if m["name"] == doc["best"])
    detail = json.dumps({k: doc[k] for k in ("best", "warnings", "runs")}, default=str)[:3000]
    assert doc["best"] == "S3", detail
    assert abs(best["wave_speed"] - 353.73) <= 0.5, detail
    assert not [w for w in doc["warnings"] if w["code"] == "misfit"], detail
    assert len(doc["runs"]) == 3
    for r in doc["runs"]:
        assert {"path", "n", "noise_ratio", "disagrees", "head_sha256", "steady_flow_m3_s"} <= set(r)
        assert r["disagrees"] is False and 0.8 < r["noise_ratio"] < 1.2 and r["n"] == 8000, r
    assert sorted(round(r["steady_flow_m3_s"] * 1e3, 2) for r in doc["runs"]) == [2.5, 3.64, 4.5]
    # k counts the shared wall and every run's closure: five each (the coupling is the rig's valve law's), two
    # where its shape is held at the rig's valve (manoeuvre.choose_closure: these records are of that valve)
    closures = [r["manoeuvre"] for r in doc["runs"]]
    assert all(c["nuisance_parameters"] == (2 if c["shape"] == "rig" else 5) for c in closures), closures
    assert doc["settings"]["k_nuisance"] == sum(c["nuisance_parameters"] for c in closures)
    assert best["k"] == 7 + doc["settings"]["k_nuisance"]
    # the likelihood is the runs' n_r ln F_r summed: N ln F of the pooled F
    assert best["n"] == 24000


def test_models_far_behind_are_not_polished_again_and_say_so(joint):
    """After the closures' refinement only the models within CONTINUE_MARGIN of the best are polished again (the
    continuation's cost); the others keep their first-pass wall under the refined closures and are named."""
    from velab.fitting.joint import CONTINUE_MARGIN, CONTINUE_MARGIN_PER_SAMPLE

    doc, _, _ = joint
    skipped = doc["settings"]["not_continued"]
    aic = {m["name"]: m["aic"] for m in doc["models"]}
    assert "EL" in skipped and doc["best"] not in skipped, skipped
    margin = max(CONTINUE_MARGIN, CONTINUE_MARGIN_PER_SAMPLE * doc["n"])
    assert all(aic[name] - aic[doc["best"]] > margin for name in skipped), (skipped, aic)
    assert any(note.startswith(", ".join(skipped) + ": not polished again") for note in doc["notes"]), doc["notes"]


def test_the_joint_wave_speed_is_more_precise_than_any_single_run(joint, campaign, capsys):
    doc, _, _ = joint
    _, runs, _ = campaign
    best = next(m for m in doc["models"] if m["name"] == doc["best"])
    single = []
    for p in runs:
        capsys.readouterr()
        # (S2-S4: the neighbours of the truth, as the joint fit ranks them; the module's time)
        assert main(["fit", str(p), "--json", "--no-save", "--window", str(WINDOW), "--models", "2-4"]) == 0
        d = json.loads(capsys.readouterr().out)
        one = next(m for m in d["models"] if m["name"] == d["best"])
        single.append(one["wave_speed_se"])
    assert best["wave_speed_se"] < min(single), (best["wave_speed_se"], single)


@pytest.fixture(scope="module")
def second(campaign):
    """A second campaign of the same pipe (three runs at the same flows, other noise), fitted jointly."""
    from velab.fitting.campaignrun import CampaignRun
    from velab.fitting.joint import fit_joint

    tmp, _, _ = campaign
    runs = [_csv_run(tmp, f"s{i + 1}", q, "A", seed) for i, (q, seed) in enumerate(((2.5, 41), (3.64, 42), (4.5, 43)))]
    return fit_joint([CampaignRun.from_run(read_run(p)) for p in runs], WINDOW).to_dict()


@pytest.mark.parametrize("which", ["module", "second"])
@pytest.mark.parametrize("t_s", [0.05, 0.5, 5.0])
def test_the_true_creep_lies_in_the_joint_band(joint, second, which, t_s):
    """Head only (every run's closure fitted): the true J(t) - J0 of material A within 2.58 of the band's
    standard errors (its 99 % band) on two campaigns, and the wave speed within 2.58 of its own.

    The closure's orifice-coupling exponent used to be fitted: it came out 0.07-0.27 for a true 1 (it trades
    with the characteristic and the fast element, and its regressor, the measured head, carries the record's
    noise), the fast element took the difference and J(0.05 s) lay 3.4 standard errors above the truth here
    (0.74-0.94 % high; over eight campaigns z = +1.69 on average, three outside the 95 % band, a 1.45 of its
    standard errors high). Now the exponent is the rig's valve law's and the coupling takes the calibrated
    model's head (docs/fitting.md, "The manoeuvre"): over the same eight campaigns z = +0.04, +0.23, +0.38 on
    average at 0.05, 0.5 and 5 s (standard deviations about 1), the wave speed +0.06; one point of 24 outside
    the 95 % band -- this campaign's J(0.05 s), z = 2.09, as chance puts the largest of 24 -- hence the 99 % band
    here, which the fitted coupling failed (z = 3.4 and 2.7 on these two campaigns)."""
    doc = joint[0] if which == "module" else second
    best = next(m for m in doc["models"] if m["name"] == doc["best"])
    assert doc["best"] == "S3"
    c = best["creep"]
    t = np.array(c["t_s"])
    truth = load_material("A").creep_compliance(np.array([t_s]))[0]
    lo, hi = (float(np.exp(np.interp(np.log(t_s), np.log(t), np.log(np.array(c[k], dtype=float))))) for k in
              ("lower", "upper"))
    fit = float(np.exp(np.interp(np.log(t_s), np.log(t), np.log(np.array(c["J_per_pa"], dtype=float)))))
    z = np.log(fit / truth) / (np.log(hi / lo) / (2 * 1.96))
    assert abs(z) <= 2.58, (which, t_s, truth, fit, lo, hi, z)
    assert hi / lo < 1.5  # a band, not a blanket
    assert abs(best["wave_speed"] - 353.73) <= 2.58 * best["wave_speed_se"], (best["wave_speed"], best["wave_speed_se"])


@pytest.mark.parametrize("names", [("r1", "r2", "r3"), ("s1", "s2", "s3")])
def test_with_the_recorded_valve_position_the_band_holds(campaign, second, names):
    """The same two campaigns before their export (``velab synth``'s files: head and valve position): every
    closure from the position, none fitted. Over eight campaigns of this recipe the head-only band was too
    narrow at 0.5 and 5 s (z +0.85 and +0.93 on average, two points beyond 3); from the position z averaged
    +0.24..+0.42 with standard deviations 0.8-1.0 (docs/fitting.md, "Measured": the fitted closures' curved
    valley). Here: S3, every run driven by its position, the truth within the 99 % band at 0.05, 0.5 and 5 s."""
    from velab.fitting.campaignrun import CampaignRun
    from velab.fitting.joint import fit_joint

    tmp, _, _ = campaign
    doc = fit_joint([CampaignRun.from_run(read_run(tmp / f"synth_{n}.h5")) for n in names], WINDOW).to_dict()
    assert [r["manoeuvre"]["source"] for r in doc["runs"]] == ["position"] * 3
    assert doc["best"] == "S3"
    best = next(m for m in doc["models"] if m["name"] == "S3")
    c = best["creep"]
    t = np.array(c["t_s"])
    for t_s in (0.05, 0.5, 5.0):
        truth = load_material("A").creep_compliance(np.array([t_s]))[0]
        fit, lo, hi = (float(np.exp(np.interp(np.log(t_s), np.log(t), np.log(np.array(c[k], dtype=float)))))
                       for k in ("J_per_pa", "lower", "upper"))
        z = np.log(fit / truth) / (np.log(hi / lo) / (2 * 1.96))
        assert abs(z) <= 2.58, (names, t_s, truth, fit, lo, hi, z)
    assert abs(best["wave_speed"] - 353.73) <= 2.58 * best["wave_speed_se"], (best["wave_speed"], best["wave_speed_se"])


def test_the_joint_fit_is_saved_into_every_run_naming_the_others(joint, campaign, capsys):
    doc, before, figure = joint
    _, runs, _ = campaign
    assert figure.stat().st_size > 10_000
    for i, p in enumerate(runs):
        run = read_run(p)
        assert head_sha256(run.time_s, run.head_m) == before[p]  # the recorded data untouched
        with h5py.File(p, "r") as fh:
            g = fh["entry/fits/joint_w8s"]
            assert g.attrs["velab_fit_kind"] == "joint"
        capsys.readouterr()
        assert main(["info", str(p)]) == 0
        text = capsys.readouterr().out
        assert "joint fit joint_w8s: 3 runs, best S3" in text
        others = [q for q in runs if q != p]
        for q in others:
            assert f"other run: {q} (head sha256 {before[q][:16]}" in text
        assert f"this run: {p}" in text
        capsys.readouterr()
        assert main(["info", str(p), "--json"]) == 0
        stored = json.loads(capsys.readouterr().out)["fits"]["joint_w8s"]
        assert stored["run_index"] == i and stored["fit_kind"] == "joint"
        assert [o["head_sha256"] for o in stored["other_runs"]] == [before[q] for q in others]


def test_runs_of_another_wall_or_pipe_are_named(campaign, capsys):
    """Material B's run and a run of a longer pipe (its rig file claiming this pipe) among material A's:
    each named, with a per-run misfit warning carrying its path; the others still agree and the wall is
    still A's."""
    _, runs, others = campaign
    capsys.readouterr()
    assert main(["fit", *map(str, runs), *map(str, others), "--joint", "--json", "--no-save",
                 "--window", str(WINDOW), "--models", "2-4"]) == 0
    doc = json.loads(capsys.readouterr().out)
    misfits = [w for w in doc["warnings"] if w["code"] == "misfit"]
    assert [w["run"] for w in misfits] == list(map(str, others)), doc["warnings"]
    assert all(w["run"] in w["message"] for w in misfits)
    assert [r["disagrees"] for r in doc["runs"]] == [False, False, False, True, True]
    assert all(0.8 < r["noise_ratio"] < 1.2 for r in doc["runs"][:3]), doc["runs"]
    best = next(m for m in doc["models"] if m["name"] == doc["best"])
    assert doc["best"] == "S3" and abs(best["wave_speed"] - 353.73) <= 0.5


def test_bad_input_is_one_line_naming_the_file_and_nothing_is_written(campaign, tmp_path, capsys):
    _, runs, _ = campaign
    damaged = tmp_path / "damaged.h5"
    damaged.write_bytes(b"not a run file at all")
    another = _csv_run(tmp_path, "long_pipe", 3.64, "A", 5, length_m=150.0)
    cases = [
        ([str(runs[0]), str(tmp_path / "missing.h5")], str(tmp_path / "missing.h5")),
        ([str(runs[0]), str(damaged)], str(damaged)),
        ([str(runs[0]), str(another)], str(another)),
        ([str(runs[0]), str(runs[0])], str(runs[0])),
        ([str(runs[0])], "two or more runs"),
    ]
    files = [*runs, another]
    shas = {p: _file_sha(p) for p in files}
    for argv, named in cases:
        capsys.readouterr()
        assert main(["fit", *argv, "--joint", "--window", str(WINDOW)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and named in err, err
    assert main(["fit", str(runs[0]), str(runs[1]), "--joint", "--jobs", "2"]) == 2  # (--reduced it takes now)
    assert "--jobs does not apply to a joint fit" in capsys.readouterr().err
    assert {p: _file_sha(p) for p in files} == shas


def test_the_stacked_evaluator_is_the_runs_weighted_rows():
    """Each run's rows, weighted, bit for bit what its own evaluator gives: the runs are evaluated in two groups,
    one on the fit's helper thread, and the result must not depend on which thread ran which run."""
    rig = load_rig("perugia")
    t1, t2, t3 = np.arange(0, 2000) / 1000.0, np.arange(0, 1500) / 500.0, np.arange(0, 3000) / 1000.0
    evs = [HeadEvaluator(rig, t1, band_hz=None),
           HeadEvaluator(rig.with_changes(steady_flow_m3_s=2.5e-3), t2, band_hz=None),
           HeadEvaluator(rig.with_changes(steady_flow_m3_s=4.5e-3), t3, band_hz=None)]
    weights = (2.0, 0.5, 1.5)
    st = StackedEvaluator(evs, weights)
    J, tau = np.array([0.04, 0.4]), np.array([0.2, 2.0])
    h, jac = st.head_jac_x(353.0, J, tau, True)
    for e, w, sl in zip(evs, weights, st.slices()):
        he, je = e.head_jac_x(353.0, J, tau, True)
        assert np.array_equal(h[sl], w * he) and np.array_equal(jac[:, sl], w * je)
        assert np.array_equal(st.head(353.0, J, tau)[sl], w * e.head(353.0, J, tau))
    assert st.n_t == 6500 and st.slices()[1] == slice(2000, 3500)


def test_runs_may_differ_in_rate_manoeuvre_and_valve_input():
    """A 2 kHz run with its recorded valve position beside a 1 kHz head-only run with a slower actuator at
    another flow (the time-domain model, real butterfly valve, quadratic friction): the true model and
    wave speed; each run at its own fit rate; only the head-only run's closure counted as nuisance."""
    from velab.fitting.campaignrun import CampaignRun
    from velab.fitting.joint import fit_joint
    from velab.model import creep_scale
    from velab.moc import moc_head
    from velab.valvelaw import commanded_position_pct

    A = load_material("A")
    base = load_rig("perugia")
    sources = []
    for i, (q0, beta, fs, with_position) in enumerate(((3.64, 32.0, 2000.0, True), (2.8, 27.0, 1000.0, False))):
        m = base.manoeuvre
        rig = base.with_changes(steady_flow_m3_s=q0 / 1e3,
                                manoeuvre=type(m)(beta_per_s=beta, gamma=-beta * m.half_closure_s))
        a = A.wave_speed_m_s
        J = creep_scale(rig, a) * np.array([e.J_per_pa for e in A.elements])
        tau = np.array([e.tau_s for e in A.elements])
        t = np.arange(-int(0.6 * fs), int(6.0 * fs)) / fs

        def position(x, beta=beta, gamma=rig.manoeuvre.gamma):
            return commanded_position_pct(x, beta, gamma)

        h = rig.steady_head_m + moc_head(rig, a, J, tau, t, position=position)
        h = h + np.random.default_rng(30 + i).normal(0.0, 0.1, t.size)
        pos = position(t) + np.random.default_rng(40 + i).normal(0.0, 0.02, t.size) if with_position else None
        sources.append(CampaignRun(f"run{i}", t, h, 0.0, rig, fs, pos, head_sha256(t, h)))
    r = fit_joint(sources, 6.0, models="1-4")
    assert r.best.name == "S3" and abs(r.best.wave_speed_m_s - 353.73) <= 0.5, format_report(r)
    assert [x["record_rate_hz"] for x in r.runs] == [2000.0, 1000.0]
    assert [x["sample_rate_hz"] for x in r.runs] == [1000.0, 1000.0]  # 2 kHz fitted at 1 kHz (prepare_record)
    assert [x["manoeuvre"]["source"] for x in r.runs] == ["position", "fitted"]
    assert r.settings["k_nuisance"] == r.runs[1]["manoeuvre"]["nuisance_parameters"] in (2, 5)
    assert r.best.k == 7 + r.settings["k_nuisance"]
    # the runs' table says how each run's flow at the valve was obtained
    from velab.fitting.jointresult import runs_report

    rows = runs_report(r).splitlines()[2:]
    shape = "rig's shape" if r.runs[1]["manoeuvre"]["shape"] == "rig" else "fitted shape"
    assert "position" in rows[0] and shape in rows[1], rows
    assert not r.warnings and not any(x["disagrees"] for x in r.runs), r.warnings
