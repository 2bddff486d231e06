"""Property-based tests of the CSV importer: any text or bytes gives a record that makes sense or
one DataError naming the file (and the line when it is a line's fault); never a traceback or a hang."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzzing import Hang, time_limit
from velab.config import load_rig
from velab.csvimport import MIN_SAMPLES, PRESSURE_UNITS, read_csv_record
from velab.errors import DataError

pytestmark = pytest.mark.timeout(600)
RIG = load_rig("perugia")

_NUMBER_TEXT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**6, 10**6).map(str),
    st.sampled_from(["", " ", "nan", "inf", "-inf", "1e400", "1,5", "0x10", "--1", "1e", ".", "+", "1_0", "NaN"]),
    st.text(max_size=6),
)


@st.composite
def csv_texts(draw):
    """CSV-like text: a header (or not), rows of mostly numbers, a delimiter, noise in places."""
    delim = draw(st.sampled_from([",", ";", "\t", " ", "|"]))
    header = draw(st.one_of(st.just(["time", "head"]), st.lists(st.text(max_size=6), max_size=4),
                            st.just(["0", "1"])))
    n = draw(st.integers(0, 40))
    regular = draw(st.booleans())
    rate = draw(st.sampled_from([1000.0, 10.0, 1e-3, 1e6]))
    rows = []
    for i in range(n):
        if regular and draw(st.integers(0, 9)) > 0:
            rows.append([repr(i / rate - 0.005), repr(30.0 + draw(st.floats(-5, 5)))])
        else:
            rows.append(draw(st.lists(_NUMBER_TEXT, min_size=0, max_size=4)))
    lines = [delim.join(header)] + [delim.join(r) for r in rows]
    if draw(st.booleans()):
        lines.insert(draw(st.integers(0, len(lines))), draw(st.text(max_size=20)))
    return "\n".join(lines) + draw(st.sampled_from(["", "\n", "\r\n", "\n\n"]))


def check_record(path, units: str, **kw):
    try:
        with time_limit(10.0):
            rec = read_csv_record(path, RIG, units=units, **kw)
    except DataError as exc:
        msg = str(exc)
        assert "\n" not in msg and str(path) in msg, msg
        return None
    except Hang:
        pytest.fail(f"the importer hung on {path.read_bytes()[:500]!r}")
    # accepted: it must make sense
    assert rec.time_s.size == rec.head_m.size >= MIN_SAMPLES
    assert np.isfinite(rec.time_s).all() and (np.diff(rec.time_s) > 0).all()
    assert np.isfinite(rec.head_m).all() or units != "m"
    assert math.isfinite(rec.sample_rate_hz) and rec.sample_rate_hz > 0
    return rec


@given(text=csv_texts(), units=st.sampled_from(list(PRESSURE_UNITS)))
def test_csv_text_imports_or_fails_in_one_line(text, units, tmp_path_factory):
    path = tmp_path_factory.mktemp("csv") / "rec.csv"
    path.write_text(text, encoding="utf-8")
    check_record(path, units)


@given(data=st.binary(max_size=2000), units=st.sampled_from(list(PRESSURE_UNITS)),
       columns=st.sampled_from([(None, None), ("time", "head"), ("head", "time"), ("x", None)]))
def test_csv_bytes_import_or_fail_in_one_line(data, units, columns, tmp_path_factory):
    path = tmp_path_factory.mktemp("csv") / "rec.csv"
    path.write_bytes(data)
    check_record(path, units, time_column=columns[0], value_column=columns[1])


def test_regular_csv_is_read_exactly(tmp_path):
    path = tmp_path / "rec.csv"
    t = np.arange(-50, 200) / 1000.0
    path.write_text("time,head\n" + "".join(f"{float(a)!r},{30 + float(a)!r}\n" for a in t))
    rec = check_record(path, "m")
    assert rec is not None and rec.sample_rate_hz == pytest.approx(1000.0)
    np.testing.assert_array_equal(rec.time_s, t)


def test_special_files_refused_before_reading(tmp_path):
    import os

    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    for path, reason in (("/dev/zero", "not a regular file"), (fifo, "not a regular file"),
                         (tmp_path, "is a directory"), (tmp_path / "none.csv", "no such file")):
        with time_limit(10.0), pytest.raises(DataError, match=reason):
            read_csv_record(path, RIG)
