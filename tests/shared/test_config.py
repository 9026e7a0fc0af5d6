"""shared/config.py: ``--set`` overrides of nested frozen dataclasses (the SLAM's, the map
server's), and the map server's and the demo's ``--set`` / ``--server-set``."""

import numpy as np
import pytest

from fleet_slam.cli import main
from map_server.config import FleetConfig
from robot_agent.slam.config import ConfigError as SlamConfigError
from robot_agent.slam.config import command_line_config
from shared.config import ConfigError, apply_overrides


def test_fleet_overrides_reach_nested_sections_and_keep_types():
    cfg = apply_overrides(
        FleetConfig(),
        ["mature_window_s=45", "alignment.min_overlap_m=40", "contradiction.enabled=off", "confirmations=3",
         "alignment.vote_cell_rad=0.1"],
    )  # fmt: skip
    assert cfg.mature_window_s == 45.0 and isinstance(cfg.mature_window_s, float)
    assert cfg.alignment.min_overlap_m == 40.0 and cfg.contradiction.enabled is False
    assert cfg.confirmations == 3 and isinstance(cfg.confirmations, int)
    assert cfg.alignment.vote_cell_rad == 0.1 and isinstance(cfg.alignment.vote_cell_rad, np.floating)
    assert cfg.alignment.min_share == FleetConfig().alignment.min_share  # the rest untouched
    assert apply_overrides(FleetConfig(), ["compiled=false"]).alignment.compiled is False


@pytest.mark.parametrize(
    ("override", "names"),
    [
        ("mature_window=3", ["'mature_window'", "mature_window_s"]),  # unknown: the known ones listed
        ("alignment.nope=1", ["'alignment.nope'"]),
        ("confirmations=two", ["confirmations", "expected int", "'two'"]),
        ("contradiction.enabled=maybe", ["contradiction.enabled", "boolean"]),
        ("alignment=3", ["alignment is a section"]),
        ("alignment.refine_stages=1", ["alignment.refine_stages (tuple) cannot be set from a string"]),
        ("mature_window_s", ["must look like section.key=value"]),
    ],
)
def test_a_bad_override_names_what_is_wrong(override, names):
    with pytest.raises(ConfigError) as e:
        apply_overrides(FleetConfig(), [override])
    for n in names:
        assert n in str(e.value)


def test_the_slam_overrides_are_the_same_machinery():
    assert SlamConfigError is ConfigError
    assert command_line_config(["proposal.point_sigma_m=0.03"]).proposal.point_sigma_m == 0.03
    with pytest.raises(ConfigError, match="unknown config key 'nope'"):
        command_line_config(["nope=1"])


def test_the_server_refuses_a_bad_override_before_it_takes_the_state(tmp_path, capsys):
    state = tmp_path / "state"
    argv = ["server", "--connect", "tcp/127.0.0.1:9", "--state", str(state), "--set", "mature_window=3"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "fleet-slam server: error:" in err and "'mature_window'" in err
    assert not state.exists()  # no lock taken, no directory made


def test_the_demo_refuses_a_bad_server_override_before_it_starts_anything(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--server-set", "alignment.nope=1"]) == 2
    assert "'alignment.nope'" in capsys.readouterr().err
    assert not out.exists()
