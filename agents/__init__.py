"""Retriever-0 and its worlds: agents built on Retriever's public API."""
