"""``python -m map_server`` = ``fleet-slam server`` (what the container runs): the same arguments and the
same error handling (a message and exit 2 or 130, never a traceback, for bad input, a missing router
or a signal while waiting for it: shared.entry), without the ``fleet-slam`` command line that
holds the other side too."""

import sys

from map_server.service import SUMMARY, add_arguments, run
from shared.entry import service_main

if __name__ == "__main__":
    sys.exit(service_main("server", SUMMARY, add_arguments, run))
