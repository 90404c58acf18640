"""``python -m omg.tools.bench KIND ...``: the data benchmark's worker, one loader measured in its own
process (``omg.tools.bench.data.worker_main``; ``omg bench data`` starts it by this module path)."""

import sys

from omg.tools.bench.data import worker_main

if __name__ == "__main__":
    worker_main(sys.argv[1:])
