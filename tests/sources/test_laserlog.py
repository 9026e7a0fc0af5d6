"""LaserLog: per-scan beam geometry held as a table of distinct geometries, scans cut to their beams."""

from __future__ import annotations

import numpy as np
import pytest

from robot_agent.sources import LaserLog, Scan
from robot_agent.sources.carmen import flaser_angles


def _varying() -> LaserLog:
    """Four scans: 3 beams, 2 beams, the first geometry again, 3 beams at other angles."""
    angles = np.array([[-1.0, 0.0, 1.0], [-0.5, 0.5, 99.0], [-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0]])
    ranges = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 77.0], [6.0, np.inf, 7.0], [8.0, 9.0, 10.0]])
    return LaserLog.from_arrays(
        [1.0, 2.0, 3.0, 4.0], ranges, angles, np.arange(12.0).reshape(4, 3), (0.2, 0, 0), 20.0,
        beam_counts=[3, 2, 3, 3],
    )  # fmt: skip


def test_distinct_geometries_are_stored_once_in_order_of_first_use():
    log = _varying()
    np.testing.assert_array_equal(log.scan_geometry, [0, 1, 0, 2])
    np.testing.assert_array_equal(log.geometry_beams, [3, 2, 3])
    np.testing.assert_array_equal(log.beam_counts, [3, 2, 3, 3])
    np.testing.assert_array_equal(log.angle_table_rad, [[-1, 0, 1], [-0.5, 0.5, np.nan], [-2, 0, 2]])
    assert log.kind == "ROBOTLASER1"


def test_scan_is_cut_to_its_own_beams():
    log = _varying()
    second = log.scan(1)
    assert isinstance(second, Scan) and second.stamp_s == 2.0 and second.range_max_m == 20.0
    np.testing.assert_array_equal(second.ranges_m, [4.0, 5.0])  # the 77.0 past 2 beams is gone
    np.testing.assert_array_equal(second.angles_rad, [-0.5, 0.5])
    np.testing.assert_array_equal(second.odometry, [3.0, 4.0, 5.0])
    np.testing.assert_array_equal(log.scan(-1).angles_rad, [-2.0, 0.0, 2.0])
    assert np.isinf(log.scan(2).ranges_m[1])  # a reading's own inf is kept
    assert [s.stamp_s for s in log.scans()] == [1.0, 2.0, 3.0, 4.0]
    with pytest.raises(IndexError):
        log.scan(4)


def test_padding_is_nan_and_every_array_read_only():
    log = _varying()
    assert np.isnan(log.ranges_m[1, 2]) and np.isnan(log.angle_table_rad[1, 2])
    for name in ("ranges_m", "angle_table_rad", "scan_geometry", "geometry_beams", "stamps_s"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(log, name)[0] = 0
    with pytest.raises(ValueError, match="read-only"):
        log.scan(0).ranges_m[0] = 0.0


def test_one_angles_array_for_all_scans_still_works():
    log = LaserLog.from_arrays([1.0, 2.0], np.ones((2, 181)), flaser_angles(181), np.zeros((2, 3)))
    assert log.kind == "FLASER" and log.angle_table_rad.shape == (1, 181)
    np.testing.assert_array_equal(log.scan(1).angles_rad, flaser_angles(181))
    # and with fewer beams in some scans: their leading angles
    log = LaserLog.from_arrays(
        [1.0, 2.0], np.ones((2, 3)), [-1.0, 0.0, 1.0], np.zeros((2, 3)), beam_counts=[3, 2]
    )
    np.testing.assert_array_equal(log.scan(1).angles_rad, [-1.0, 0.0])
    assert log.kind == "ROBOTLASER1"


def test_range_limit_inferred_from_the_beams_only():
    ranges = np.full((20, 4), 3.0)
    ranges[:, 1] = 8.5  # a recurring largest reading: a "no return" code
    ranges[:, 3] = 50.0  # padding: never a reading
    log = LaserLog.from_arrays(
        np.arange(20.0), ranges, flaser_angles(3 + 1), np.zeros((20, 3)), beam_counts=[3] * 20
    )
    assert log.range_max_m == 8.5


def test_inconsistent_tables_are_refused():
    base = dict(
        stamps_s=[1.0], ranges_m=[[1.0, 2.0]], angle_table_rad=[[0.0, 1.0]], geometry_beams=[2],
        scan_geometry=[0], odometry=[[0, 0, 0]], laser_offset=[0, 0, 0], range_max_m=5.0,
        odom_stamps_s=[], odom_poses=np.zeros((0, 3)),
    )  # fmt: skip
    LaserLog(**base)
    with pytest.raises(ValueError, match=r"scan_geometry must index the 1 geometries"):
        LaserLog(**base | {"scan_geometry": [1]})
    with pytest.raises(ValueError, match=r"geometry_beams must lie in \[0, 2\]"):
        LaserLog(**base | {"geometry_beams": [3]})
    with pytest.raises(ValueError, match=r"angle_table_rad has shape \(1, 3\).*B=2"):
        LaserLog(**base | {"angle_table_rad": [[0.0, 1.0, 2.0]]})
