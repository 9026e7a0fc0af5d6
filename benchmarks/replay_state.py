"""A map server's saved state replayed offline: each robot's verdict as saved, then every robot not
placed searched again as the server's attempt does (Placer.estimate: the searches, the fleet's
graph's trials run at once), placed where the search places it, round after round with a fusion
between, until a round places nobody — what the server decides on the same maps, step by step,
without agents, zenoh or timing. For a placing change: restore the state of a live run that went
wrong (bench_demo keeps each run's: ``<out>/<run>/state``) and see what the change decides there
(session 56: ACES in 3 pieces left pieces unplaced; every live verdict and trial came out again to
the decimetre).

    .venv/bin/python benchmarks/replay_state.py /tmp/bd/aces-split3-seed10/state [--rounds 3]
        [--set alignment.min_share=0.12 ...] [--json benchmarks/results/replay_state.json]

The state directory is read, never written. Prints each robot's map length and how much of its walls
stand in its own free space (what its checks allow for; over ``graph.consistent_self_m`` it is a
bent piece), then one row per verdict (round, robot, status, place, why), and writes them as JSON.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _results import save_results

from map_server.config import FleetConfig
from map_server.freespace import FreeSpaces
from map_server.server import decode_state
from map_server.store import Store
from shared.config import apply_overrides


def restore(state_dir: str | Path, cfg: FleetConfig):
    """The fleet a server's state directory holds, its robots' free spaces known to it (as a
    restarted server's); the directory is only read."""
    loaded = Store(state_dir, check=False).load()
    if loaded is None:
        raise SystemExit(f"{state_dir}: no saved state in it")
    return decode_state(*loaded, cfg, "replay_state", FreeSpaces())[0]


def _row(round_: int, robot: str, a) -> dict:
    return dict(
        round=round_, robot=robot, status=a.status, transform=[float(x) for x in a.transform], reason=a.reason
    )


def replay(fleet, rounds: int, now_s: float = 1e6) -> list[dict]:
    """Round 0: each robot's saved verdict. Then up to ``rounds`` rounds: every robot with a map
    that is not placed searched (Placer.estimate) and put where its search places it; a fusion
    after each round; stop after a round that places nobody."""
    rows = [_row(0, name, r.alignment) for name, r in sorted(fleet.robots.items())]
    for k in range(1, rounds + 1):
        placed = 0
        for name, r in sorted(fleet.robots.items()):
            if r.layer is None or r.alignment.placed:
                continue
            v = fleet.placer.estimate(r, None, None, None, search=True)
            rows.append(_row(k, name, v))
            if v.placed:
                r.alignment = v
                placed += 1
        fleet.fuse(now_s + k)
        if not placed:
            break
    return rows


def self_contradiction(fleet) -> dict[str, dict]:
    """Each robot's map length and how much of its walls stand in its own free space (m; None:
    its free space not known) — what its checks allow for and what makes it a bent piece
    (Placer.own_noise_m against graph.consistent_self_m). ACES in 3 pieces: the first piece 5-9 m
    on five live runs' final maps, 16.7 m on the one that left it unplaced (session 57)."""
    out = {}
    for name, r in sorted(fleet.robots.items()):
        if r.layer is not None:
            out[name] = dict(length_m=float(r.layer.length_m), self_m=fleet.placer.own_noise_m(r))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("state", help="a map server's state directory (its index and blobs)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--set", nargs="+", default=[], metavar="SECTION.KEY=VALUE", help="FleetConfig override")
    ap.add_argument("--json", default="benchmarks/results/replay_state.json")
    args = ap.parse_args(argv)
    fleet = restore(args.state, apply_overrides(FleetConfig(), args.set))
    noise = self_contradiction(fleet)
    rows = replay(fleet, args.rounds)
    print(f"reference {fleet.reference}")
    for name, n in noise.items():
        own = "its free space not known"
        if n["self_m"] is not None:
            own = f"{n['self_m']:.1f} m in its own free space"
        print(f"{name}: {n['length_m']:.0f} m of walls, {own}")
    for r in rows:
        where = np.array2string(np.round(r["transform"], 3), separator=", ")
        print(f"round {r['round']}  {r['robot']:10s} {r['status']:10s} {where:28s} {r['reason']}")
    out = dict(state=str(args.state), reference=fleet.reference, self_contradiction=noise, rows=rows)
    save_results(args.json, "replay_state", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
