"""The Archive tab's fit requests (velab.gui.archive_io, no Qt): a re-fit and a joint fit carry the Re-fit
settings' search (issue 51: every option for every kind of fit), and bad settings are refused when the request
is made, before anything is submitted."""

import pytest

from velab.errors import DataError
from velab.gui.archive_io import RefitOptions, joint_request, refit_request


def test_a_joint_fit_takes_the_refit_settings_search():
    opts = RefitOptions(models="1-3", window_s=8.0, method="nelder-mead", starts=2, polish=False)
    r = joint_request(["a.h5", "b.h5"], opts)
    c = r.choices
    assert (c.models, c.method, c.starts, c.polish) == ((1, 2, 3), "nelder-mead", 2, False)
    assert r.window_s == 8.0 and r.source.paths == ("a.h5", "b.h5")
    single = refit_request("a.h5", opts).choices
    assert (single.method, single.starts, single.polish) == (c.method, c.starts, c.polish)


def test_bad_refit_settings_are_refused_when_the_request_is_made():
    with pytest.raises(DataError, match="starts"):
        joint_request(["a.h5", "b.h5"], RefitOptions(starts=0))
    with pytest.raises(DataError, match="fit method"):
        refit_request("a.h5", RefitOptions(method="simplex"))
