"""The ``smcd-rl`` experiments and benchmarks: one module per command, its config in :mod:`.configs`.

This package's ``__init__`` imports nothing, and :mod:`.configs` imports no torch, so that the
command line can build its ``--help`` without the seconds torch takes to import.
"""
