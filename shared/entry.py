"""A command's run with the project's error handling — a message and exit 2 (bad input, a missing
file, no router in time) or 130 (interrupted, or a signal while waiting for the router), never a
traceback — and the entry point of a service run on its own (``python -m map_server``,
``python -m robot_agent``: what the containers run), so that neither side imports the other
through the ``fleet-slam`` command line that holds them all."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

Command = Callable[[argparse.Namespace], int | None]


def run_command(name: str, func: Command, args: argparse.Namespace) -> int:
    """``func(args)``'s exit code; domain errors (``ValueError``, ``OSError``) and the bus's
    (``BusError``) as one line on standard error, ``fleet-slam <name>: …``."""
    try:
        return int(func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError) as exc:  # domain errors derive from ValueError
        print(f"fleet-slam {name}: error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        from shared.bus import BusError  # here, not at the top: --help stays instant (no zenoh import)

        if not isinstance(exc, BusError):
            raise
        # no router in time, or a signal while waiting for it: a message, not a traceback
        print(f"fleet-slam {name}: {exc}", file=sys.stderr)
        return 130 if "cancelled" in str(exc) else 2


def service_main(
    name: str,
    summary: str,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    func: Command,
    argv: Sequence[str] | None = None,
) -> int:
    """``fleet-slam <name>`` alone: the same arguments (``add_arguments``), the same
    handling (:func:`run_command`)."""
    p = argparse.ArgumentParser(prog=f"fleet-slam {name}", description=summary)
    add_arguments(p)
    return run_command(name, func, p.parse_args(argv))
