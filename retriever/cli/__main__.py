"""``python -m retriever.cli``: the ``retriever`` command."""

from . import main

if __name__ == "__main__":
    main()
