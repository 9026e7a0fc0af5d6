"""``python -m map_server`` = ``fleet-slam server`` (what the container runs)."""

import argparse
import sys

from map_server.service import add_arguments, run

if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m map_server", description="the fleet-slam map server")
    add_arguments(parser)
    try:
        sys.exit(run(parser.parse_args()))
    except (ValueError, OSError) as exc:
        print(f"map_server: error: {exc}", file=sys.stderr)
        sys.exit(2)
