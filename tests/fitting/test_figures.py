"""The figures people print (issue 50): the fit report figure (``velab fit --plot``, the Archive's export)
and the joint campaign figure are titled with the run(s), rig, date and best model; their panels say what
they show (head minus the steady head), the ΔAIC thresholds are named and 0 has a place on its axis, the
noise band stays over the data, and bands and legends say 95 % where they are 95 %."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from velab.cli import main as velab_main  # noqa: E402


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    from velab.fitting.entry import fit_run
    from velab.runfiles import read_run

    d = tmp_path_factory.mktemp("fig")
    runs = []
    for seed in (1, 2):
        p = d / f"run{seed}.h5"
        assert velab_main(["synth", "--material", "A", "--duration", "3", "--seed", str(seed), "-q", "-o", str(p)]) == 0
        runs.append(read_run(p))
    result = fit_run(runs[0], 2.0, models=range(0, 2), starts=1, polish=False)
    return d, runs, result


def _legend_texts(ax) -> list[str]:
    leg = ax.get_legend()
    return [t.get_text() for t in leg.get_texts()] if leg is not None else []


def test_report_figure_is_titled_and_labelled(fitted):
    from velab.fitting.plots import report_figure

    d, runs, result = fitted
    run = runs[0]
    t, h = run.fit_window(2.0)
    fig = report_figure(t, h, run.rig, result, d / "report.png", run=run)
    assert (d / "report.png").stat().st_size > 10000
    title = fig._suptitle.get_text()
    assert "run1.h5" in title and run.rig.name in title and "recorded " + run.start_time[:10] in title
    assert f"best model {result.best.name}" in title
    head, aic = fig.axes[0], fig.axes[1]
    assert "steady" in head.get_ylabel() and "steady" in head.get_title()
    assert aic.get_yscale() == "log"
    ys = np.concatenate([ln.get_ydata() for ln in aic.lines if len(ln.get_ydata())])
    assert ys.min() >= 1.0  # 1 + ΔAIC: the best model's 0 sits at 1 on the log axis
    labels = _legend_texts(aic)
    assert any(s.startswith("ΔAIC = 2") for s in labels) and any(s.startswith("ΔAIC = 10") for s in labels)
    assert "0" in [t.get_text() for t in aic.get_yticklabels()]  # the axis is read in ΔAIC
    res = fig.axes[-1]
    lo, hi = res.get_xlim()
    tr = res.lines[0].get_xdata()
    assert lo >= tr[0] - 1e-9 and hi <= tr[-1] + 1e-9  # the noise band not past the data
    for coll in res.collections:
        xs = np.concatenate([p.vertices[:, 0] for p in coll.get_paths()])
        assert xs.min() >= tr[0] - 1e-9 and xs.max() <= tr[-1] + 1e-9
    assert any("SD of the baseline noise" in s for s in _legend_texts(res))


def test_campaign_figure_says_95_percent_and_names_its_band(fitted):
    from velab.fitting.campaign import campaign_figure
    from velab.fitting.campaignrun import CampaignRun
    from velab.fitting.joint import fit_joint

    d, runs, _ = fitted
    sources = [CampaignRun.from_run(r) for r in runs]
    result = fit_joint(sources, 2.0, models=[1])
    fig = campaign_figure(result, d / "joint.png", sources)
    title = fig._suptitle.get_text()
    assert "joint fit of 2 runs" in title and runs[0].rig.name in title and "recorded" in title
    ax_a = fig.axes[1]
    labels = _legend_texts(ax_a)
    assert any(s.startswith("joint a = ") and "95 %" in s for s in labels), labels
    assert "joint a, 95 % interval" in labels  # the grey band has its entry
    assert "95 %" in ax_a.get_ylabel()
