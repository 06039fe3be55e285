"""``python -m retriever``: the ``retriever`` command."""

from .cli import main

main()
