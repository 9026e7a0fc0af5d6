"""Bus latency on loopback: put -> subscriber callback, through a router, one message at a time.

A router and two client sessions in this process (``shared.bus``), all on 127.0.0.1. Each message
is put only after the previous one arrived, so the figure is latency, not queueing. Prints a
table and writes JSON.
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import numpy as np
from _results import save_results

from fleet_slam.procs import free_port
from shared.bus import Bus, BusConfig

SIZES_BYTES = (1_000, 10_000, 50_000)
WARMUP = 50  # messages not timed: routes and buffers settle


def free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def latencies_s(n_messages: int, size: int, reliable: bool, shm: bool) -> np.ndarray:
    endpoint = free_endpoint()
    arrived = threading.Event()
    stamps = {"recv": 0.0}

    def on_sample(_key: str, _payload: bytes) -> None:
        stamps["recv"] = time.perf_counter()
        arrived.set()

    out = np.empty(n_messages)
    with (
        Bus(BusConfig(mode="router", connect=(), listen=(endpoint,), shm=shm)),
        Bus(BusConfig(connect=(endpoint,), shm=shm)) as pub,
        Bus(BusConfig(connect=(endpoint,), shm=shm)) as sub,
    ):
        sub.subscribe("bench/latency", on_sample)
        payload = bytes(size)
        for i in range(-WARMUP, n_messages):
            arrived.clear()
            sent = time.perf_counter()
            pub.put("bench/latency", payload, reliable=reliable)
            while not arrived.wait(0.2):  # the first puts may precede the route: put again
                sent = time.perf_counter()
                pub.put("bench/latency", payload, reliable=reliable)
            if i >= 0:
                out[i] = stamps["recv"] - sent
    return out


def main(n_messages: int, out: Path) -> list[dict]:
    rows = []
    for size in SIZES_BYTES:
        for reliable in (True, False):
            for shm in (False, True):
                lat_ms = latencies_s(n_messages, size, reliable, shm) * 1e3
                rows.append(
                    {
                        "size_bytes": size,
                        "reliable": reliable,
                        "shm": shm,
                        "messages": n_messages,
                        "p50_ms": float(np.percentile(lat_ms, 50)),
                        "p95_ms": float(np.percentile(lat_ms, 95)),
                        "max_ms": float(lat_ms.max()),
                    }
                )
    print(f"{'size':>7} {'reliable':>8} {'shm':>5} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8}")
    for r in rows:
        print(
            f"{r['size_bytes']:7d} {r['reliable']!s:>8} {r['shm']!s:>5} "
            f"{r['p50_ms']:8.3f} {r['p95_ms']:8.3f} {r['max_ms']:8.3f}"
        )
    save_results(out, "bench_bus", {"results": rows})
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=2000, help="timed messages per case (default 2000)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/bench_bus.json"))
    args = parser.parse_args()
    main(args.messages, args.out)
