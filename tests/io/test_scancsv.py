import io

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sonarloc.errors import LogFormatError
from sonarloc.io.scancsv import ScanReadings, iter_scan_csv, read_scan_csv, write_scan_csv


def test_columns_any_order_unknown_ignored_empty_is_no_echo():
    text = ("tof_us,comment,yaw_deg,t_s,y_m,x_m\n"
            "8746,a,4.0,0.0,0,0\n,b,4.3,0.1,0,0\nnan,c,4.6,0.1,0,0\n")
    scan = read_scan_csv(io.StringIO(text))
    assert len(scan) == 3
    assert scan.tof_us[0] == 8746.0 and np.isnan(scan.tof_us[1:]).all()
    np.testing.assert_allclose(np.rad2deg(scan.yaw_rad), [4.0, 4.3, 4.6])
    assert (scan.sensor == 0).all()


def test_byte_order_mark_is_not_part_of_the_header():
    # a spreadsheet's "CSV UTF-8" starts with one; it read as a missing `t_s` column
    text = "\ufefft_s,x_m,y_m,yaw_deg,tof_us,sensor\n0,0,0,4,8746,2\n"
    scan = read_scan_csv(io.StringIO(text))
    assert len(scan) == 1 and scan.t_s[0] == 0.0 and scan.sensor[0] == 2


def test_sensor_ids_of_64_bits_read_exactly():
    text = ("t_s,x_m,y_m,yaw_deg,tof_us,sensor\n"
            "0,0,0,0,1,9223372036854775807\n0,0,0,0,1,-9223372036854775808\n")
    assert read_scan_csv(io.StringIO(text)).sensor.tolist() == [2**63 - 1, -(2**63)]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "line 1: empty"),
        ("t_s,x_m,y_m,tof_us\n0,0,0,1\n", "lacks column.*yaw_deg"),
        # a European spreadsheet's export: the delimiter is named, not just the columns
        ("t_s;x_m;y_m;yaw_deg;tof_us\n0;0;0;0;1\n",
         "lacks column.*one field with semicolons in it: the columns must be separated by "
         "commas"),
        ("t_s\tx_m\ty_m\tyaw_deg\ttof_us\n0\t0\t0\t0\t1\n", "one field with tabs"),
        ("t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,0,1\n0.1,zero,0,0,1\n", "line 3: column `x_m`"),
        ("t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,0,1\n\n0.1,0,0,nan,1\n", "line 4: column `yaw_deg`"),
        ("t_s,x_m,y_m,yaw_deg,tof_us\n1,0,0,0,1\n0.5,0,0,0,1\n", "line 3: `t_s` went backwards"),
        ("t_s,x_m,y_m,yaw_deg,tof_us,sensor\n1,0,0,0,1,x\n", "line 2: column `sensor`"),
        ("t_s,x_m,y_m,yaw_deg,tof_us\n1,0,0\n", "line 2: 3 fields"),
        # found by the session-15 sweep (tests/fit/test_fit_fuzz.py): these raised
        # OverflowError, RuntimeError (StopIteration) and csv.Error, naming no line
        ("t_s,x_m,y_m,yaw_deg,tof_us,sensor\n1,0,0,0,1,0\n2,0,0,0,1,9223372036854775808\n",
         "line 3: column `sensor` must be a 64-bit integer"),
        ("t_s,x_m,y_m,yaw_deg,tof_us,sensor\n1,0,0,0,1,-18446744073709551616\n",
         "line 2: column `sensor`"),
        ("t_s,x_m,y_m,yaw_deg,tof_us,sensor\n1,0,0,0,1,\u00b2\n", "line 2: column `sensor`"),
        ("t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,0,1\n1,0,0,0," + "9" * 140_000 + "\n",
         "line 3: field larger than field limit"),
        # a quoted field spanning lines: the line named is the file's, not the record's
        ('t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,"1\r\n\n",1\n0.1,0,oops,0,1\n',
         "line 5: column `y_m`"),
    ],
)
def test_bad_files_name_the_line(text, match):
    with pytest.raises(LogFormatError, match=match):
        read_scan_csv(io.StringIO(text))
    for block_rows in (1, 2):     # read in blocks: the same line named, across blocks
        with pytest.raises(LogFormatError, match=match):
            list(iter_scan_csv(io.StringIO(text), block_rows))


@pytest.mark.parametrize("block_rows", [1, 2, 3, 7, 100])
def test_blocks_join_to_the_whole_file(block_rows):
    rows = [f"{0.1 * i:.1f},{i},0,{3 * i},{'' if i % 4 == 1 else 8000 + i},{i % 3}\n"
            for i in range(17)]
    rows[5:5] = ["\n", "\n"]                              # blank lines are allowed
    text = "t_s,x_m,y_m,yaw_deg,tof_us,sensor\n" + "".join(rows)
    whole = read_scan_csv(io.StringIO(text))
    blocks = list(iter_scan_csv(io.StringIO(text), block_rows))
    assert all(len(b) <= block_rows for b in blocks) and len(blocks) >= 17 // block_rows
    joined = ScanReadings.concat(blocks)
    for name, _ in ScanReadings.FIELDS:
        np.testing.assert_array_equal(getattr(joined, name), getattr(whole, name))
    assert len(whole) == 17 and whole.sensor[4] == 1
    with pytest.raises(ValueError, match="block_rows"):
        list(iter_scan_csv(io.StringIO(text), 0))


finite = st.floats(-1e4, 1e4, allow_nan=False)


@given(st.lists(st.tuples(finite, finite, finite, st.one_of(st.just(float("nan")),
                                                             st.floats(0, 6e4)),
                          st.integers(0, 31)), max_size=30))
def test_round_trip(rows):
    n = len(rows)
    arr = np.array([r[:4] for r in rows], dtype=float).reshape(n, 4)
    scan = ScanReadings(np.arange(n) * 0.01, arr[:, 0], arr[:, 1], np.deg2rad(arr[:, 2]),
                        arr[:, 3], np.array([r[4] for r in rows], dtype=np.int64))
    buf = io.StringIO()
    write_scan_csv(buf, scan)
    back = read_scan_csv(io.StringIO(buf.getvalue()))
    for name in ("t_s", "x_m", "y_m", "yaw_rad", "tof_us"):
        np.testing.assert_allclose(getattr(back, name), getattr(scan, name), rtol=1e-12,
                                   atol=1e-12)
    np.testing.assert_array_equal(back.sensor, scan.sensor)


def test_timeout_watch_counts_echoes_only_and_the_largest_across_blocks():
    from sonarloc.io.scancsv import TimeoutWatch

    w = TimeoutWatch()
    w.push(np.array([-5.0] * 50 + [np.nan] * 10 + [np.inf] * 3))  # bad readings, no echo
    assert w.suspect(echoes=0) is None
    w.push(np.array([9000.0] * 6 + [8000.0]))
    assert w.suspect(echoes=7) == (9000.0, 6)
    w.push(np.array([62000.0] * 4))   # a larger value starts the count again
    assert w.suspect(echoes=11) is None
    w.push(np.array([62000.0, 5000.0]))
    assert w.suspect(echoes=13) == (62000.0, 5)
    assert w.suspect(echoes=101) is None   # under 5 % of the echoes
