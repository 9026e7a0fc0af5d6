"""The live view's server without zenoh: the page loads nothing from elsewhere, /state and /events
carry the fused map, free space and poses, events are pushed to every viewer, a slow viewer's queue
stays bounded, and a bad --listen is refused by name."""

from __future__ import annotations

import json
import re
import threading
import urllib.request
from http.server import ThreadingHTTPServer

import numpy as np
import pytest

from fleet_slam import view
from shared.messages import FusedFree, FusedMap, PoseUpdate, RobotStatus


def fused(version: int) -> FusedMap:
    t, sigma = np.array([1.0, 2.0, 0.5]), np.array([0.01, 0.01, 0.001])
    r = RobotStatus("robot1", "prior", True, "s1", 3, 2, t, sigma)
    seg = np.array([[[0.0, 0.0], [4.0, 0.0]], [[4.0, 0.0], [4.0, 3.0]]])
    return FusedMap("server", version, 1.0, 0, 1, (r,), seg, np.ones(2, np.int64), np.array([0, 1, 2]),
                    np.zeros(2, np.int64), session="abc")  # fmt: skip


def free() -> FusedFree:
    sq = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    no_walls = np.zeros((0, 2, 2))
    return FusedFree("server", "abc", 1, 1, 1.0, 0.02, np.array([0, 4]), np.array([0]), sq, no_walls)


def test_the_page_is_self_contained():
    html = view.PAGE.read_text()
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", html)  # nothing from the internet
    assert "EventSource" in html and "window.fleetView" in html


@pytest.fixture
def served():
    state, stop = view.ViewState(), threading.Event()
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), view.make_handler(state, stop))
    httpd.daemon_threads = True
    t = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    t.start()
    yield state, f"http://127.0.0.1:{httpd.server_address[1]}"
    stop.set()
    httpd.shutdown()
    httpd.server_close()
    t.join(5)


def test_state_and_events_carry_the_map_free_space_and_poses(served):
    state, url = served
    state.on_map(fused(7))
    state.on_free(free())
    state.on_pose(PoseUpdate("robot1", "s1", 0, 2.0, np.array([0.5, 0.0, 0.1]), {"odometry_doubt": 0.0}))
    st = json.loads(urllib.request.urlopen(url + "/state", timeout=5).read())
    assert st["map"]["version"] == 7 and len(st["map"]["segments"]) == 2
    assert st["map"]["robots"][0]["transform"] == [1.0, 2.0, 0.5] and st["free"]["polygons"]
    assert st["paths"]["robot1"][0][:4] == ["s1", 0.5, 0.0, 0.1]
    with urllib.request.urlopen(url + "/events", timeout=5) as events:
        first = events.readline().decode()
        data = json.loads(events.readline().decode().removeprefix("data: "))
        assert first == "event: state\n" and data["map"]["version"] == 7
        events.readline()
        state.on_map(fused(8))  # pushed, no reloading
        assert events.readline().decode() == "event: map\n"
        assert json.loads(events.readline().decode().removeprefix("data: "))["version"] == 8
    assert urllib.request.urlopen(url + "/", timeout=5).read().startswith(b"<!doctype html>")
    with pytest.raises(urllib.error.HTTPError, match="404"):
        urllib.request.urlopen(url + "/nothing", timeout=5)


def test_a_slow_viewer_loses_old_events_not_memory():
    state = view.ViewState()
    q = state.join()
    for v in range(view.CLIENT_QUEUE * 3):
        state.on_map(fused(v + 1))
    assert q.qsize() == view.CLIENT_QUEUE  # the newest; the oldest were dropped
    last = None
    while not q.empty():
        last = q.get_nowait()
    assert b'"version":%d' % (view.CLIENT_QUEUE * 3) in last
    state.leave(q)


def test_poses_are_thinned_to_the_view_rate_and_paths_bounded():
    state = view.ViewState()
    for i in range(50):  # a burst: one pose kept
        state.on_pose(PoseUpdate("robot1", "s1", i, float(i), np.zeros(3)))
    assert len(state.paths["robot1"]) == 1
    assert state.paths["robot1"].maxlen == view.PATH_POSES


@pytest.mark.parametrize("text", ["8090", "localhost", "127.0.0.1:port", ":8090", "127.0.0.1:70000"])
def test_a_bad_listen_address_is_refused(text):
    with pytest.raises(ValueError, match="--listen: expected HOST:PORT"):
        view.parse_listen(text)
