"""Load: does the map server keep up with a fleet of 32 agents (maps 1 Hz, poses 5 Hz) for 2 minutes,
and how does it degrade when overloaded?

    .venv/bin/python benchmarks/bench_load.py [--agents 32] [--seconds 120] [--quick]
        [--scenario normal overload] [--overload-map-hz 5] [--min-gap 0.05] [--window 10]
        [--profile] [--cache DIR] [--refresh] [--workdir DIR] [--out FILE]

Real processes on loopback, as ``bench_fleet.py``'s latency part: a router, the map server (state
persisted in ``--workdir``) and N load agents, **one process each** (``bench_fleet.py load-agent``:
``robot_agent.agent.Publisher`` replaying a recorded real agent map sequence with a start prior).
There are 24 recordings; agent i replays recording i mod 24, and each further round of 24 is laid
out ``BAND_GAP_M`` further along y, so no two agents publish the same map in the same place.

Scenarios: ``normal`` (maps 1 Hz, poses 5 Hz) and ``overload`` (maps at ``--overload-map-hz``,
5 Hz by default: five times the map traffic the server is built for). Each: start-up, every robot
placed, ``--warmup`` s, then ``--seconds`` measured, then every agent stopped at once and the
server left to drain.

The server is seen through what it publishes: every fused map carries ``server_*`` figures in
``FusedMap.extra`` (maps waiting at the tick that produced it, the previous fusion's time, the
cumulative maps per fusion, fusions, peak RSS). This process subscribes to the fused map and keeps,
per fused map, its arrival time, the ``server_*`` figures and each robot's ``map_seq``; a thread
samples VmRSS and CPU time of the server, the router and the agents from ``/proc`` every second.
Latency of map ``seq`` of robot r = arrival of the first fused map with ``map_seq(r) >= seq`` - the
agent's ``time.monotonic()`` just before its put (system-wide clock). A map is *lost* when no fused
map reflects it or a later map of the same robot; the final fused map must show every agent's
last map.

Verdicts: no growing backlog (the last third's queue depth, p90, within the first third's max plus
slack, and its latency p95 within 1.5x the first's plus slack), memory plateau (server RSS growth
over the second half), coalescing when overloaded (maps per fusion > 1 when maps arrive faster
than the server's cycle: its fusion time, and at least ``--min-gap`` between two fusions),
nothing lost, drained (the last fused map soon after the last put).

Prints a table per scenario and writes ``benchmarks/results/bench_load.json``.
"""

from __future__ import annotations

import argparse
import itertools
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import bench_fleet as fleet  # noqa: E402
from _results import save_results  # noqa: E402

from shared import codec  # noqa: E402
from shared.geometry import compose  # noqa: E402
from shared.messages import FusedMap, WireFormatError  # noqa: E402

BAND_GAP_M = 20.0  # between two rounds of agents replaying the same recordings (no cross-band merging)
STARTUP_TIMEOUT_S = 240.0  # 32 Python processes importing numpy and zenoh on 2 busy cores
SAMPLE_PERIOD_S = 1.0  # /proc sampling
QUIET_S = 3.0  # after the agents stop: no fused map for this long = drained
DRAIN_TIMEOUT_S = 60.0
QUEUE_SLACK_MAPS = 2  # backlog verdict: the last third's queue p90 may exceed the first's max by this ...
QUEUE_SLACK_SHARE = 0.25  # ... or by this share of it, whichever is larger
LATENCY_SLACK_MS = 50.0  # backlog verdict: the last third's latency p95 within 1.5x the first's + this
RSS_GROWTH_MB = 16.0  # memory verdict: server RSS growth over the second half at most this ...
RSS_GROWTH_SHARE = 0.05  # ... or this share of the RSS at half time, whichever is larger
DRAIN_BOUND_S = 2.0  # drain verdict: last fused map at most this long after the last put
CLK_TCK = os.sysconf("SC_CLK_TCK")
SCENARIOS = ("normal", "overload")
OURS = ("server_cpu", "router_cpu", "agents_cpu", "bench_cpu")  # the rest of the machine's CPU: other jobs


# -- what this process sees: fused maps and /proc samples ----------------------------------------------


class FusedLog:
    """Subscriber to the fused map that keeps, per complete fused map, only its arrival
    (``time.monotonic()``), version, segment count, every robot's ``map_seq`` (-1 when absent) and
    the ``server_*`` extras; ``latest`` is the last fused map itself (for ``_wait_placed``)."""

    def __init__(self, bus, keys, robots: list[str]):
        self.bus, self.keys, self.robots = bus, keys, robots
        self._index = {r: i for i, r in enumerate(robots)}
        self._assembler = codec.Assembler()
        self._lock = threading.Lock()
        self.latest: FusedMap | None = None
        self.arrival: list[float] = []
        self.version: list[int] = []
        self.segments: list[int] = []
        self.seqs: list[np.ndarray] = []
        self.extra: list[dict] = []
        self.rejected = 0

    def start(self) -> None:
        self.bus.subscribe(self.keys.fused, self._on_payload)

    def _on_payload(self, _key: str, payload: bytes) -> None:
        t = time.monotonic()
        try:
            done = self._assembler.add(codec.decode(payload, expect=FusedMap))
        except WireFormatError:
            with self._lock:
                self.rejected += 1
            return
        if done is None:
            return
        seqs = np.full(len(self.robots), -1, np.int64)
        for s in done.robots:
            if (i := self._index.get(s.robot)) is not None:
                seqs[i] = s.map_seq
        with self._lock:
            self.latest = done
            self.arrival.append(t)
            self.version.append(done.version)
            self.segments.append(len(done.seg))
            self.seqs.append(seqs)
            self.extra.append({k: v for k, v in done.extra.items() if k.startswith("server_")})

    def count(self) -> int:
        with self._lock:
            return len(self.arrival)

    def last_seqs(self) -> np.ndarray | None:
        """Each robot's map seq in the last fused map received (-1: not in it), or None."""
        with self._lock:
            return self.seqs[-1] if self.seqs else None

    def last_arrival(self) -> float:
        with self._lock:
            return self.arrival[-1] if self.arrival else 0.0

    def arrays(self) -> dict:
        """Everything as arrays: ``arrival (U,)``, ``seqs (U,N)``, one ``(U,)`` per extra key."""
        with self._lock:
            keys = sorted({k for e in self.extra for k in e})
            return {
                "arrival": np.array(self.arrival), "version": np.array(self.version),
                "segments": np.array(self.segments),
                "seqs": np.array(self.seqs).reshape(len(self.seqs), len(self.robots)),
                **{k: np.array([e.get(k, np.nan) for e in self.extra]) for k in keys},
            }  # fmt: skip


def _proc_figures(pid: int) -> tuple[float, float]:
    """(VmRSS MB, user + system CPU seconds) of ``pid`` from /proc; (nan, nan) once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return np.nan, np.nan
    rss = [float(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:")]
    rss_kb = rss[0] if rss else np.nan  # a zombie has no VmRSS
    fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) ": field 3 is fields[0]
    return rss_kb / 1024.0, (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime


def _machine_busy_s() -> float:
    """CPU seconds the whole machine has been busy (all cores; /proc/stat minus idle and iowait)."""
    ticks = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (sum(ticks[:8]) - ticks[3] - ticks[4]) / CLK_TCK  # user nice system idle iowait irq softirq steal


class Sampler(threading.Thread):
    """Every ``SAMPLE_PERIOD_S``: monotonic time, then RSS (MB) and CPU (s) of the server, the router,
    the agents (summed) and this process, the machine's busy CPU seconds, the 1-minute load average."""

    COLUMNS = ("t", "server_rss", "server_cpu", "router_rss", "router_cpu", "agents_rss", "agents_cpu",
               "bench_cpu", "machine_cpu", "load1")  # fmt: skip

    def __init__(self, server: int, router: int, agents: list[int]):
        super().__init__(daemon=True)
        self.server, self.router, self.agents = server, router, agents
        self.rows: list[tuple] = []
        self._done = threading.Event()

    def run(self) -> None:
        while not self._done.is_set():
            agents = np.array([_proc_figures(p) for p in self.agents]).reshape(-1, 2)
            t = os.times()
            self.rows.append((
                time.monotonic(), *_proc_figures(self.server), *_proc_figures(self.router),
                *np.nansum(agents, axis=0), t.user + t.system, _machine_busy_s(), os.getloadavg()[0],
            ))  # fmt: skip
            self._done.wait(SAMPLE_PERIOD_S)

    def stop(self) -> dict:
        self._done.set()
        self.join()
        a = np.array(self.rows).reshape(-1, len(self.COLUMNS))
        return {c: a[:, i] for i, c in enumerate(self.COLUMNS)}


# -- one run -----------------------------------------------------------------------------------------


def agent_priors(recs: list, n: int) -> list[np.ndarray]:
    """Agent i replays ``recs[i % len(recs)]``; round k of them is shifted by k bands along y."""
    from robot_agent.sim import builtin_world

    base = fleet.latency_priors(recs)
    band_m = max(b[3] - b[1] for b in (builtin_world(w).bounds for w in fleet.WORLDS)) + BAND_GAP_M
    return [compose(np.array([0.0, (i // len(recs)) * band_m, 0.0]), base[i % len(recs)]) for i in range(n)]


@dataclass
class LoadRun:
    scenario: str
    agents: int
    map_hz: float
    min_gap_s: float
    window: tuple[float, float]  # measured, monotonic
    stop_s: float  # when every agent was told to stop
    fused: dict  # FusedLog.arrays()
    samples: dict  # Sampler.stop()
    puts: list  # per agent: (seqs (P,), monotonic put times (P,))
    final_seqs: np.ndarray  # (N,) in the last fused map, -1 when absent
    final_placed: int
    server_log: str
    profile: Path | None = None
    notes: list = field(default_factory=list)


def _start_agents(group, recs, n, endpoint, fleet_id, map_hz, run_dir) -> list:
    priors, rng = agent_priors(recs, n), np.random.default_rng(n)
    agents = []
    for i in range(n):
        robot = f"robot{i + 1:02d}"
        argv = [sys.executable, fleet.__file__, "load-agent", "--robot", robot, "--connect", endpoint,
                "--fleet", fleet_id, "--recording", recs[i % len(recs)].path,
                "--prior", ",".join(f"{v:.9g}" for v in priors[i]), "--puts", run_dir / f"{robot}.puts",
                "--phase", f"{rng.uniform(0, 1):.3f}", "--first-map", fleet.FIRST_REPLAYED_MAP,
                "--map-period", 1.0 / map_hz, "--pose-period", 0.2]  # fmt: skip
        agents.append(group.start(robot, [str(a) for a in argv]))
    for a in agents:
        _wait(a, "connected")
    return agents


def _wait(proc, text: str) -> None:
    if not proc.wait_for(text, STARTUP_TIMEOUT_S):
        raise RuntimeError(f"{proc.name} did not start; see {proc.log_path}:\n{proc.output()[-2000:]}")


def _stop_agents(agents: list) -> None:
    """SIGTERM to all at once (so the fleet stops together), then reap each."""
    for a in agents:
        if a.running:
            a.popen.send_signal(signal.SIGTERM)
    for a in agents:
        a.stop()


def _drain(log: FusedLog, last_seqs: np.ndarray) -> None:
    """Wait until a fused map shows every agent's last put (``last_seqs (N,)``, in the order of
    ``log.robots``), at most ``DRAIN_TIMEOUT_S``; an agent that put nothing is not waited for. (A
    quiet spell alone is no sign of it: the server may be busy with a long fusion, e.g. the
    settle after every robot left at once.)"""
    end = time.monotonic() + DRAIN_TIMEOUT_S
    while time.monotonic() < end:
        seqs = log.last_seqs()
        if seqs is not None and np.all(seqs >= last_seqs):
            break
        time.sleep(0.1)
    while time.monotonic() < end and time.monotonic() - log.last_arrival() < QUIET_S:
        time.sleep(0.1)  # and the versions after it (the settle's) have come


def run_load(recs, scenario: str, n: int, map_hz: float, seconds: float, warmup_s: float,
             min_gap_s: float, workdir: Path, profile: bool) -> LoadRun:  # fmt: skip
    """Router, server, ``n`` load agents, this process watching; the measured window, then drain."""
    from fleet_slam.procs import ProcGroup, free_port, python_module
    from shared.bus import Bus, BusConfig
    from shared.keys import Keys

    run_dir = workdir / f"{scenario}-{n}"
    shutil.rmtree(run_dir, ignore_errors=True)  # this benchmark's own earlier run
    run_dir.mkdir(parents=True)
    endpoint, fleet_id = f"tcp/127.0.0.1:{free_port()}", "load"
    robots = [f"robot{i + 1:02d}" for i in range(n)]
    with ProcGroup(run_dir / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        _wait(router, "listening")
        server = group.start("server", python_module(
            "map_server", "--connect", endpoint, "--state", run_dir / "state", "--fleet", fleet_id,
            "--min-gap", min_gap_s))  # fmt: skip
        _wait(server, "running")
        with Bus(BusConfig(connect=(endpoint,))) as bus:
            log = FusedLog(bus, Keys(fleet_id), robots)
            log.start()
            t_start = time.monotonic()
            agents = _start_agents(group, recs, n, endpoint, fleet_id, map_hz, run_dir)
            print(f"  {n} agents connected in {time.monotonic() - t_start:.0f} s", flush=True)
            sampler = Sampler(server.popen.pid, router.popen.pid, [a.popen.pid for a in agents])
            sampler.start()
            try:
                fleet._wait_placed(log, robots, STARTUP_TIMEOUT_S)
                print(f"  every robot placed after {time.monotonic() - t_start:.0f} s", flush=True)
                time.sleep(warmup_s)
                spy_out = run_dir / "server.pyspy.txt" if profile else None
                spy = fleet.start_profiler(server.popen.pid, seconds, spy_out) if profile else None
                t0 = time.monotonic()
                try:
                    _sleep_reporting(log, seconds)
                finally:
                    t1 = time.monotonic()
                    fleet.stop_profiler(spy, wait=t1 - t0 >= seconds)
                t_stop = time.monotonic()
                fleet.check_alive(agents)
                _stop_agents(agents)
                last = [fleet._read_puts(run_dir / f"{r}.puts")[0] for r in robots]
                _drain(log, np.array([s[-1] if len(s) else -1 for s in last], np.int64))
            finally:
                samples = sampler.stop()
            final = log.latest
            fused = log.arrays()
        server.stop()
        server_log = server.output()
    puts = [fleet._read_puts(run_dir / f"{r}.puts") for r in robots]
    final_seqs = fused["seqs"][-1] if len(fused["arrival"]) else np.full(n, -1)
    placed = sum(s.merged for s in final.robots) if final is not None else 0
    has_profile = profile and spy_out.exists()
    return LoadRun(scenario, n, map_hz, min_gap_s, (t0, t1), t_stop, fused, samples, puts, final_seqs, placed,
                   server_log, spy_out if has_profile else None)  # fmt: skip


def _sleep_reporting(log: FusedLog, seconds: float) -> None:
    """Sleep ``seconds``, printing a progress line every 30 s."""
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        time.sleep(min(30.0, left))
        print(f"  {seconds - max(0.0, end - time.monotonic()):.0f} s: {log.count()} fused maps", flush=True)


# -- figures -----------------------------------------------------------------------------------------


def put_latencies(run: LoadRun) -> tuple[np.ndarray, np.ndarray]:
    """Every put of every agent: its time ``(P,)`` and latency ``(P,)`` in s (nan: never reflected)."""
    arrival, seqs = run.fused["arrival"], run.fused["seqs"]
    times, lats = [], []
    for i, (seq, t) in enumerate(run.puts):
        lat = np.full(len(seq), np.nan)
        if len(arrival):
            best = np.maximum.accumulate(seqs[:, i])
            k = np.searchsorted(best, seq)  # the first fused map with map_seq >= seq
            ok = k < len(best)
            lat[ok] = arrival[k[ok]] - t[ok]
        times.append(t)
        lats.append(lat)
    return np.concatenate(times), np.concatenate(lats)


def _pct(values, q: float) -> float | None:
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    return float(np.percentile(values, q)) if len(values) else None


def _max(values) -> float | None:
    values = np.asarray(values, float)
    return float(np.nanmax(values)) if np.isfinite(values).any() else None


def span_figures(run: LoadRun, lo: float, hi: float, t_put: np.ndarray, lat: np.ndarray) -> dict:
    """The server's figures between ``lo`` and ``hi`` (monotonic): from the fused maps that arrived
    then, the puts made then and the /proc samples."""
    f, s = run.fused, run.samples
    u = (f["arrival"] >= lo) & (f["arrival"] < hi)
    p = (t_put >= lo) & (t_put < hi)
    idx = np.flatnonzero(u)
    applied = np.round(f["server_maps_per_fusion"] * f["server_fusions"])  # cumulative maps applied
    mpf = None
    if len(idx):
        prev = max(idx[0] - 1, 0)
        fusions = f["server_fusions"][idx[-1]] - f["server_fusions"][prev]
        mpf = float((applied[idx[-1]] - applied[prev]) / fusions) if fusions > 0 else None
    cpu = lambda name: _cpu_pct(s, name, lo, hi)  # noqa: E731
    q = f["server_queue_maps"][u]
    return {
        "maps_put_per_s": float(p.sum() / (hi - lo)),
        "fused_per_s": float(u.sum() / (hi - lo)),
        "queue_maps_mean": float(q.mean()) if len(q) else None,
        "queue_maps_p90": _pct(q, 90),
        "queue_maps_max": _max(q),
        "queue_poses_p90": _pct(f["server_queue_poses"][u], 90),
        "queue_poses_max": _max(f["server_queue_poses"][u]),
        "maps_per_fusion": mpf,
        "fuse_p50_ms": _pct(f["server_fuse_ms_last"][u], 50),
        "fuse_p95_ms": _pct(f["server_fuse_ms_last"][u], 95),
        "fuse_max_ms": _max(f["server_fuse_ms_last"][u]),
        # the fleet graph's matching and solve, after the fused map is out (not in fuse_*)
        "graph_p50_ms": _pct(f["server_bend_ms_last"][u], 50) if "server_bend_ms_last" in f else None,
        "graph_p95_ms": _pct(f["server_bend_ms_last"][u], 95) if "server_bend_ms_last" in f else None,
        "latency_p50_ms": _pct(lat[p] * 1e3, 50),
        "latency_p95_ms": _pct(lat[p] * 1e3, 95),
        "latency_max_ms": _max(lat[p] * 1e3),
        "server_rss_mb": float(np.interp(hi, s["t"], s["server_rss"])),
        "server_cpu_pct": cpu("server_cpu"),
        "router_rss_mb": float(np.interp(hi, s["t"], s["router_rss"])),
        "router_cpu_pct": cpu("router_cpu"),
        "agents_cpu_pct": cpu("agents_cpu"),
        "bench_cpu_pct": cpu("bench_cpu"),
        "others_cpu_pct": cpu("machine_cpu") - sum(cpu(k) for k in OURS),
        "load1": _max(s["load1"][(s["t"] >= lo) & (s["t"] <= hi)]),
    }


def _cpu_pct(s: dict, name: str, lo: float, hi: float) -> float:
    """Per cent of one core used by the sampled CPU seconds ``s[name]`` between ``lo`` and ``hi``."""
    return float((np.interp(hi, s["t"], s[name]) - np.interp(lo, s["t"], s[name])) / (hi - lo) * 100)


def windows(run: LoadRun, window_s: float, t_put, lat) -> list[dict]:
    t0, t1 = run.window
    edges = t0 + window_s * np.arange(max(1, round((t1 - t0) / window_s)) + 1)
    edges[-1] = t1  # the last window takes the measured window's few extra milliseconds
    return [
        {"t_s": f"{a - t0:.0f}-{b - t0:.0f}"} | span_figures(run, a, b, t_put, lat)
        for a, b in itertools.pairwise(edges)
    ]


def _rss_near(s: dict, t: float, half_width_s: float = 2.5) -> float:
    near = np.abs(s["t"] - t) <= half_width_s
    rss = s["server_rss"]
    return float(np.nanmedian(rss[near])) if near.any() else float(np.interp(t, s["t"], rss))


def verdicts(run: LoadRun, t_put, lat, whole: dict) -> dict:
    t0, t1 = run.window
    third = (t1 - t0) / 3
    first = span_figures(run, t0, t0 + third, t_put, lat)
    last = span_figures(run, t1 - third, t1, t_put, lat)
    out = {}
    # backlog: the last third's queue depth (maps, poses; its p90, as single spikes follow the CPU
    # other jobs take) within the first third's max + slack, its latency p95 within 1.5x + slack
    ok, text = True, []
    for what in ("maps", "poses"):
        qf, ql = first[f"queue_{what}_max"] or 0.0, last[f"queue_{what}_p90"] or 0.0
        ok &= ql <= qf + max(QUEUE_SLACK_MAPS, QUEUE_SLACK_SHARE * qf)
        text.append(f"queue {what}: first third max {qf:.0f}, last third p90 {ql:.0f} max "
                    f"{last[f'queue_{what}_max'] or 0:.0f}")  # fmt: skip
    lf, ll = first["latency_p95_ms"] or 0.0, last["latency_p95_ms"] or np.inf
    ok &= ll <= 1.5 * lf + LATENCY_SLACK_MS
    f = run.fused
    u = (f["arrival"] >= t0) & (f["arrival"] < t1)
    trend = np.polyfit(f["arrival"][u], f["server_queue_maps"][u], 1)[0] * 60 if u.sum() > 2 else np.nan
    out["backlog_not_growing"] = {
        "ok": bool(ok),
        "text": "; ".join(text) + f"; latency p95 first/last third {lf:.0f}/{ll:.0f} ms; queue trend "
                f"{trend:+.2f} maps/min; other jobs' CPU first/last third {first['others_cpu_pct']:.0f}/"
                f"{last['others_cpu_pct']:.0f} %",
    }  # fmt: skip
    # memory: server RSS growth over the second half
    s = run.samples
    half, end = _rss_near(s, (t0 + t1) / 2), _rss_near(s, t1 - 2.5)
    second = (s["t"] >= (t0 + t1) / 2) & (s["t"] <= t1) & np.isfinite(s["server_rss"])
    fit = np.polyfit(s["t"][second], s["server_rss"][second], 1) if second.sum() > 2 else [np.nan]
    slope = float(fit[0] * 60)
    bound = max(RSS_GROWTH_MB, RSS_GROWTH_SHARE * half)
    out["memory_plateau"] = {
        "ok": bool(end - half <= bound),
        "text": f"server RSS {half:.0f} MB at half time -> {end:.0f} MB at the end (+{end - half:.1f}, "
                f"bound {bound:.0f}); slope {slope:.2f} MB/min over the second half",
    }  # fmt: skip
    # coalescing: more than one map per fusion once maps arrive faster than the server's cycle (a
    # fusion, and at least the minimum gap between two)
    gap_ms = 1e3 / (run.agents * run.map_hz)
    fuse, mpf = whole["fuse_p50_ms"] or 0.0, whole["maps_per_fusion"] or 0.0
    cycle = max(fuse, run.min_gap_s * 1e3)
    over = cycle > gap_ms
    out["coalescing"] = {
        "ok": bool(mpf > 1.0 or not over),
        "text": f"map inter-arrival {gap_ms:.1f} ms vs the server's cycle {cycle:.0f} ms (fusion p50 "
                f"{fuse:.0f}, min gap {run.min_gap_s * 1e3:.0f}): {'overloaded' if over else 'keeps up'}; "
                f"{mpf:.2f} maps per fusion",
    }  # fmt: skip
    # nothing lost: every put reflected; the final fused map shows every agent's last map, placed
    last_seq = np.array([seq[-1] if len(seq) else 0 for seq, _ in run.puts])
    lost = int(np.isnan(lat).sum())
    behind = [f"robot{i + 1:02d}" for i in np.flatnonzero(run.final_seqs != last_seq)]
    out["nothing_lost"] = {
        "ok": bool(lost == 0 and not behind and run.final_placed == run.agents),
        "text": f"{len(lat)} maps put, {lost} never reflected; final fused map: {run.agents - len(behind)}"
                f"/{run.agents} at their last map seq, {run.final_placed} placed"
                + (f"; behind: {' '.join(behind[:8])}" if behind else ""),
    }  # fmt: skip
    # drained: the first fused map with every agent's last map, soon after the last put
    f = run.fused
    t_last_put = max(t[-1] for _, t in run.puts if len(t))
    done = np.flatnonzero((f["seqs"] >= last_seq).all(axis=1)) if len(f["arrival"]) else []
    drain = float(f["arrival"][done[0]] - t_last_put) if len(done) else np.inf
    out["drained"] = {"ok": bool(drain <= DRAIN_BOUND_S),
                      "text": f"every last map fused {drain:.2f} s after the last put"}  # fmt: skip
    return {"first_third": first, "last_third": last, "verdicts": out}


def status_lines(server_log: str) -> list[str]:
    return [line.split("status: ", 1)[1] for line in server_log.splitlines() if "status: " in line]


def callback_share(path: Path) -> dict:
    """Share of py-spy samples (all threads) in the server's bus callbacks: map and pose decoding
    competes with the fusion loop for the GIL."""
    counts = {"on_map": 0, "on_pose": 0, "main": 0}
    for line in path.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        for name, mark in (("on_map", "MapServer.on_map ("), ("on_pose", "MapServer.on_pose (")):
            if mark in stack:
                counts[name] += int(n)
        if "MainThread" in stack.split(";", 1)[0]:
            counts["main"] += int(n)
    main = max(counts.pop("main"), 1)
    return {f"{k}_samples_per_main_sample": v / main for k, v in counts.items()}


def summarize(run: LoadRun, window_s: float) -> dict:
    t_put, lat = put_latencies(run)
    t0, t1 = run.window
    whole = span_figures(run, t0, t1, t_put, lat)
    f, s = run.fused, run.samples
    in_window = (s["t"] >= t0) & (s["t"] <= t1)
    summary = {
        "scenario": run.scenario, "agents": run.agents, "agents_per_process": 1, "map_hz": run.map_hz,
        "pose_hz": 5.0, "min_gap_s": run.min_gap_s, "seconds": t1 - t0, **whole,
        "fusions": int(f["server_fusions"][-1]) if len(f["arrival"]) else 0,
        "fused_maps_received": len(f["arrival"]),
        "fused_segments": int(f["segments"][-1]) if len(f["arrival"]) else 0,
        "server_peak_rss_mb": _max(f.get("server_peak_rss_mb", [np.nan])),
        "server_rejected": _max(f.get("server_rejected", [np.nan])),
        "agents_rss_mb_total": _max(s["agents_rss"][in_window]),
        "router_rss_max_mb": _max(s["router_rss"][in_window]),
    }  # fmt: skip
    out = {
        "summary": summary, "windows": windows(run, window_s, t_put, lat), **verdicts(run, t_put, lat, whole),
        "server_status_lines": status_lines(run.server_log),
        "samples": {k: np.round(v, 3).tolist() for k, v in s.items()},
    }  # fmt: skip
    if run.profile is not None:
        fusions = int(((f["arrival"] >= t0) & (f["arrival"] < t1)).sum())
        parts = fleet.server_profile(run.profile, t1 - t0, fusions)
        out["server_profile"] = parts | callback_share(run.profile)
    return out


# -- output ------------------------------------------------------------------------------------------

WINDOW_COLUMNS = {
    "t_s": "t s", "maps_put_per_s": "maps put/s", "fused_per_s": "fused/s", "queue_maps_mean": "queue maps",
    "queue_maps_max": "q maps max", "queue_poses_max": "q poses max", "maps_per_fusion": "maps/fusion",
    "fuse_p50_ms": "fuse p50", "fuse_p95_ms": "fuse p95", "fuse_max_ms": "fuse max",
    "graph_p50_ms": "graph p50", "graph_p95_ms": "graph p95",
    "latency_p50_ms": "lat p50", "latency_p95_ms": "lat p95", "server_rss_mb": "server MB",
    "server_cpu_pct": "server %cpu", "router_rss_mb": "router MB", "others_cpu_pct": "others %cpu",
    "load1": "load1",
}  # fmt: skip


def print_run(res: dict) -> None:
    s = res["summary"]
    rows = [{WINDOW_COLUMNS[k]: w.get(k) for k in WINDOW_COLUMNS} for w in res["windows"]]
    rows.append({WINDOW_COLUMNS[k]: s.get(k) for k in WINDOW_COLUMNS} | {"t s": "all"})
    fleet.table(
        f"{s['scenario']}: {s['agents']} agents (one process each), maps {s['map_hz']:g} Hz, poses 5 Hz, "
        f"{s['seconds']:.0f} s, min gap {s['min_gap_s']:g} s; queue = maps waiting at a fusion's tick; "
        "fuse = the server's fuse + persist (ms); lat = agent put -> fused map received (ms); "
        "%cpu of one core (2 cores); others = the machine's CPU not used by this benchmark's processes",
        rows,
    )
    print(
        f"  {s['fusions']} fusions, {s['fused_maps_received']} fused maps received, {s['fused_segments']} "
        f"fused segments; server peak RSS {s['server_peak_rss_mb']:.0f} MB, router max "
        f"{s['router_rss_max_mb']:.0f} MB, agents {s['agents_rss_mb_total']:.0f} MB and "
        f"{s['agents_cpu_pct']:.0f} % CPU in all, this process {s['bench_cpu_pct']:.0f} % CPU; "
        f"rejected {s['server_rejected']:.0f}"
    )
    if res["server_status_lines"]:
        print(f"  server's last status line: {res['server_status_lines'][-1]}")
    if "server_profile" in res:
        parts = ", ".join(f"{k} {v:.2f}" for k, v in res["server_profile"].items())
        print(f"  server profile (py-spy): {parts}")
    for name, v in res["verdicts"].items():
        print(f"  {'PASS' if v['ok'] else 'FAIL'} {name}: {v['text']}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agents", type=int, default=None, help="agent processes (32; --quick 8)")
    ap.add_argument("--seconds", type=float, default=None, help="measured s per scenario (120; --quick 30)")
    ap.add_argument("--quick", action="store_true", help="a fast check: 8 agents, 30 s, 5 s windows")
    ap.add_argument("--scenario", choices=SCENARIOS, nargs="+", default=list(SCENARIOS))
    ap.add_argument("--map-hz", type=float, default=1.0, help="normal: maps per second per agent")
    ap.add_argument("--overload-map-hz", type=float, default=5.0, help="overload: maps per second per agent")
    ap.add_argument("--min-gap", type=float, default=0.05, help="the server's --min-gap (s between fusions)")
    ap.add_argument("--warmup", type=float, default=None, help="seconds after every robot is placed (10)")
    ap.add_argument("--window", type=float, default=None, help="seconds per reported window (10; --quick 5)")
    ap.add_argument("--profile", action="store_true", help="sample the server with py-spy during the window")
    ap.add_argument("--cache", type=Path, default=ROOT / "benchmarks" / "results" / "bench_fleet_maps",
                    help="recordings (shared with bench_fleet.py)")  # fmt: skip
    ap.add_argument("--refresh", action="store_true", help="record the simulated agents again")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_load"), help="logs and server state")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "bench_load.json")
    args = ap.parse_args(argv)
    q = args.quick
    n = args.agents or (8 if q else 32)
    seconds = args.seconds or (30.0 if q else 120.0)
    warmup, window = args.warmup or (5.0 if q else 10.0), args.window or (5.0 if q else 10.0)
    signal.signal(signal.SIGTERM, _interrupt)  # a terminated benchmark stops its processes too
    recs = fleet.recordings(args.cache, min(n, len(fleet.RUNS)), 30.0 if q else fleet.RECORD_S, args.refresh)
    results: dict = {"loadavg_at_start": os.getloadavg(), "quick": q, "agents": n, "seconds": seconds,
                     "recordings": [r.name for r in recs], "runs": {}}  # fmt: skip
    for scenario in args.scenario:
        map_hz = args.map_hz if scenario == "normal" else args.overload_map_hz
        load1 = os.getloadavg()[0]
        print(f"{scenario}: {n} agents, maps {map_hz:g} Hz, {seconds:g} s (load {load1:.2f})", flush=True)
        run = run_load(recs, scenario, n, map_hz, seconds, warmup, args.min_gap, args.workdir, args.profile)
        results["runs"][scenario] = summarize(run, window)
        print_run(results["runs"][scenario])
    results["loadavg_at_end"] = os.getloadavg()
    print(f"load average at start {results['loadavg_at_start']}, at end {results['loadavg_at_end']}")
    save_results(args.out, "bench_load", results)
    return 0


def _interrupt(*_) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":
    sys.exit(main())
