"""``python -m retriever.backends.zenoh.worker SPEC.json NODE [MODE]``: a worker process (the
package's docstring; command.py builds and reads that line)."""

import sys

from . import main

if __name__ == "__main__":
    main(sys.argv[1:])
