"""velab.filters against scipy.signal, the functions it stands in for on the fit path.

Each of ours must give scipy's numbers to 1e-12 of the signal's scale (on x86-64 they are the same to the
last bit: the same operations in the same order), for the orders, cutoffs, lengths and shapes the fit path
can meet and beyond: a fit's result must not depend on which of the two filtered its record.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal as ss

from velab import filters as F

RNG = np.random.default_rng(20261202)


def close(ours, theirs, rtol=1e-12):
    ours, theirs = np.asarray(ours), np.asarray(theirs)
    assert ours.shape == theirs.shape
    scale = float(np.nanmax(np.abs(theirs))) if theirs.size else 0.0
    np.testing.assert_allclose(ours, theirs, rtol=rtol, atol=rtol * scale)


def walk(shape, axis=-1):
    """A random walk plus noise: a record's low frequencies and its noise, offset from zero."""
    x = RNG.standard_normal(shape)
    return np.cumsum(x, axis=axis) + 0.3 * RNG.standard_normal(shape) + 12.0


# (cutoff, sample rate): the coupling's 62 Hz at 1 and 50 kHz, low and high relative cutoffs, rates not whole
CUTOFFS = [(62.0, 1000.0), (62.0, 50000.0), (0.5, 1000.0), (240.0, 1000.0), (499.0, 1000.0), (3.3, 17.1)]


@pytest.mark.parametrize("order", range(1, 9))
@pytest.mark.parametrize("fc,fs", CUTOFFS)
def test_butterworth_sections_and_steady_state_are_scipys(order, fc, fs):
    sos = F.butter_lowpass_sos(order, fc, fs)
    ref = ss.butter(order, fc, fs=fs, output="sos")
    close(sos, ref, rtol=1e-13)
    close(F.sosfilt_zi(sos), ss.sosfilt_zi(ref))
    # what it is: unit gain at DC, -3 dB at the cutoff
    w, resp = ss.freqz_sos(sos, worN=[0.0, fc], fs=fs)
    assert abs(resp[0]) == pytest.approx(1.0, abs=1e-9)
    assert abs(resp[1]) == pytest.approx(2 ** -0.5, rel=1e-6)


@pytest.mark.parametrize("bad", [(0, 10.0, 100.0), (4, 0.0, 100.0), (4, 50.0, 100.0), (4, 70.0, 100.0), (4, -1.0, 100.0)])
def test_butterworth_refuses_what_is_not_a_lowpass(bad):
    with pytest.raises(ValueError):
        F.butter_lowpass_sos(*bad)


@pytest.mark.parametrize("order", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("shape,axis", [((5000,), -1), ((3, 800), -1), ((800, 3), 0), ((2, 300, 3), 1)])
def test_sosfilt_with_and_without_initial_state(order, shape, axis):
    sos = F.butter_lowpass_sos(order, 62.0, 1000.0)
    x = walk(shape, axis)
    close(F.sosfilt(sos, x, axis=axis), ss.sosfilt(sos, x, axis=axis))
    zshape = list(shape)
    zshape[axis] = 2
    zi = RNG.standard_normal([sos.shape[0]] + zshape)
    given = zi.copy()
    y, zf = F.sosfilt(sos, x, axis=axis, zi=zi)
    assert np.array_equal(zi, given)  # the caller's state is not touched
    y_ref, zf_ref = ss.sosfilt(sos, x, axis=axis, zi=zi)
    close(y, y_ref)
    close(zf, zf_ref)
    with pytest.raises(ValueError):
        F.sosfilt(sos, x, axis=axis, zi=zi[:, :1])


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 8])
@pytest.mark.parametrize("fc,fs", CUTOFFS)
@pytest.mark.parametrize("n", [1745, 20000])
def test_sosfiltfilt_1d(order, fc, fs, n):
    sos = F.butter_lowpass_sos(order, fc, fs)
    x = walk(n)
    given = x.copy()
    close(F.sosfiltfilt(sos, x), ss.sosfiltfilt(sos, x))
    assert np.array_equal(x, given)


@pytest.mark.parametrize("order", [2, 3, 4])
@pytest.mark.parametrize("shape,axis", [((4, 3000), -1), ((3000, 4), 0), ((2, 500, 3), 1), ((2, 3, 400), 2)])
def test_sosfiltfilt_2d_and_3d_along_any_axis(order, shape, axis):
    sos = F.butter_lowpass_sos(order, 40.0, 1000.0)
    x = walk(shape, axis)
    close(F.sosfiltfilt(sos, x, axis=axis), ss.sosfiltfilt(sos, x, axis=axis))


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5])
def test_sosfiltfilt_default_padding_and_its_length_limit(order):
    """The padding is 3 (2 n_sections + 1 - min(#b2 = 0, #a2 = 0)) samples (an odd order's first-order section
    counts one tap less); x must be longer than that, as in scipy."""
    sos = F.butter_lowpass_sos(order, 62.0, 1000.0)
    ntaps = 2 * sos.shape[0] + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    edge = 3 * ntaps
    x = walk(edge + 1)
    close(F.sosfiltfilt(sos, x), ss.sosfiltfilt(sos, x))
    for n in (edge, 2):
        with pytest.raises(ValueError):
            ss.sosfiltfilt(sos, walk(n))
        with pytest.raises(ValueError):
            F.sosfiltfilt(sos, walk(n))


def test_sosfiltfilt_is_zero_phase_and_keeps_a_line():
    """What it is: away from the ends a straight line passes unchanged and a slow sine is not delayed."""
    sos = F.butter_lowpass_sos(4, 62.0, 1000.0)
    t = np.arange(4000) / 1000.0
    close(F.sosfiltfilt(sos, 3.0 + 2.0 * t)[500:-500], 3.0 + 2.0 * t[500:-500], rtol=1e-9)
    s = np.sin(2 * np.pi * 2.0 * t)
    y = F.sosfiltfilt(sos, s)
    assert np.max(np.abs(y[500:-500] - s[500:-500])) < 1e-6


@pytest.mark.parametrize("numtaps", [1, 2, 7, 8, 41, 201, 1001])
@pytest.mark.parametrize("cutoff", [0.02, 0.1, 1 / 3, 0.5, 0.9])
def test_firwin_lowpass_is_scipys(numtaps, cutoff):
    close(F.firwin_lowpass(numtaps, cutoff), ss.firwin(numtaps, cutoff, window="hamming"), rtol=1e-13)


@pytest.mark.parametrize("q", [2, 3, 7, 10, 50])
@pytest.mark.parametrize("n", [2, 3, 101, 1000, 12345])
def test_fir_decimate_is_resample_poly_with_line_padding(q, n):
    h = F.firwin_lowpass(20 * q + 1, 1.0 / q)
    x = walk(n)
    given = x.copy()
    close(F.fir_decimate(x, h, q), ss.resample_poly(x, 1, q, window=h, padtype="line"))
    assert np.array_equal(x, given)


@pytest.mark.parametrize("taps", [1, 2, 6, 9, 40])
def test_fir_decimate_with_any_filter_length(taps):
    h = RNG.standard_normal(taps)
    x = walk(997)
    for q in (2, 5):
        close(F.fir_decimate(x, h, q), ss.resample_poly(x, 1, q, window=h, padtype="line"))


@pytest.mark.parametrize("shape,axis", [((3, 5000), -1), ((5000, 3), 0), ((2, 999, 2), 1)])
def test_fir_decimate_2d(shape, axis):
    q = 10
    h = F.firwin_lowpass(20 * q + 1, 1.0 / q)
    x = walk(shape, axis)
    close(F.fir_decimate(x, h, q, axis=axis), ss.resample_poly(x, 1, q, window=h, padtype="line", axis=axis))


def test_fir_decimate_edge_cases():
    h = F.firwin_lowpass(41, 0.5)
    x = walk(50)
    y = F.fir_decimate(x, h, 1)  # q = 1: a copy, unfiltered (resample_poly's up == down)
    close(y, x)
    assert y is not x
    assert np.isnan(F.fir_decimate(np.array([4.0]), h, 2)).all()  # no line through a single sample
    with np.errstate(invalid="ignore"):
        assert np.isnan(ss.resample_poly(np.array([4.0]), 1, 2, window=h, padtype="line")).all()
    with pytest.raises(ValueError):
        F.fir_decimate(np.array([]), h, 2)
    with pytest.raises(ValueError):
        F.fir_decimate(x, h, 0)


def test_the_fit_paths_filters_as_it_calls_them():
    """The coupling's head (velab.fitting.flows) and the record's decimation (velab.fitting.prepare) give scipy's
    numbers: the two calls as they were written with scipy.signal."""
    from velab.config import load_rig
    from velab.fitting.flows import COUPLING_BAND_FACTOR, coupling_head
    from velab.fitting.prepare import FIR_TAPS_PER_Q, decimate_head
    from velab.model import manoeuvre_band_hz

    rig = load_rig("perugia")
    for fs in (1000.0, 10000.0):
        t = np.arange(int(3 * fs)) / fs
        h = walk(t.size)
        fc = COUPLING_BAND_FACTOR * manoeuvre_band_hz(rig)
        close(coupling_head(t, h, rig), ss.sosfiltfilt(ss.butter(4, fc, fs=fs, output="sos"), h))
    for q in (2, 10, 50):
        h = walk(20000)
        b = ss.firwin(FIR_TAPS_PER_Q * q + 1, 1.0 / q, window="hamming")
        close(decimate_head(h, q), ss.resample_poly(h, 1, q, window=b, padtype="line"))
