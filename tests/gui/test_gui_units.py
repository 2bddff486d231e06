"""The device table's values in the rig's units with the digits they deserve, and the fit summary's text
(issue 50): no 7.605e-08 %, no m3/s beside l/s; the Headline's best model, a ± SE and elements."""

from __future__ import annotations

import pytest

pytest.importorskip("PySide6")


@pytest.mark.parametrize("name, value, units, shown", [
    ("valve_position", 7.605e-08, "%", ("valve position", "0.0", "%")),
    ("valve_position", -1e-9, "%", ("valve position", "0.0", "%")),
    ("valve_position", 63.27, "%", ("valve position", "63.3", "%")),
    ("flow", 2.65e-09, "m3/s", ("flow", "0.000", "l/s")),
    ("flow", 0.0036412, "m3/s", ("flow", "3.641", "l/s")),
    ("head", 34.7163, "m", ("head at the valve", "34.72", "m")),
    ("head", float("nan"), "m", ("head at the valve", "—", "m")),
    ("temperature", 20.123456, "degC", ("temperature", "20.12", "degC")),
    ("flow", 3.6, "gal/min", ("flow", "3.6", "gal/min")),  # units the table does not know: as given
])
def test_values_in_the_rigs_units(name, value, units, shown):
    from velab.gui.devices import shown as show

    assert show(name, value, units) == shown


def test_fit_summary_renders_the_headline():
    import math

    from velab.fitting.headline import Element, Headline
    from velab.gui.fit_summary import headline_html

    h = Headline("S2", "Akaike weight 0.91 of 7 models; next S3, dAIC 4.6 (support: considerably less)", 0.91,
                 353.52, 0.015, (Element(1, 1.2e11, 6e9, 9.8e9, 1.5e8, 0.0795, 0.0035, 8.1e-12, 4e-13),
                                 Element(2, 7.4e9, math.nan, 6.2e9, 7.8e7, 0.836, 0.027, 1.36e-10, 2.8e-12, False)),
                 1.04, 1.5, "1.04x the record's own noise (chance allows up to 1.50x)",
                 ("misfit: the best model ...",))
    text = headline_html(h)
    assert "Best model S2" in text and "a = 353.52 ± 0.015 m/s" in text
    assert "1.200e+11 ± 6e+09" in text and "7.400e+09 (fixed)" in text and "0.0795 ± 0.0035" in text
    assert "noise ratio F/noise: 1.04x" in text and "misfit: the best model" in text
    assert "misfit: the best model" not in headline_html(h, warnings=False)
