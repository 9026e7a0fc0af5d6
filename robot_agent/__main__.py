"""``python -m robot_agent`` = ``fleet-slam agent`` (what the container runs)."""

import argparse
import sys

from robot_agent.service import add_arguments, run

if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m robot_agent", description="one fleet-slam robot agent")
    add_arguments(parser)
    try:
        sys.exit(run(parser.parse_args()))
    except (ValueError, OSError) as exc:
        print(f"robot_agent: error: {exc}", file=sys.stderr)
        sys.exit(2)
