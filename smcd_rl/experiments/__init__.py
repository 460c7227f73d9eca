"""The ``smcd-rl`` experiments and benchmarks: one package per command, and what they share.

Each command's package (``two_link``, ``telescoping``, ``panda``, ``interpret``, ``sweep``,
``ant``, ``fetch``, ``scoreboard``, ``bench.planners``, ``bench.filter``, ``bench.control``)
holds its torch-free ``config.py`` (what ``--help`` is built from), its ``run.py`` and the modules
only it uses; :mod:`.shared` holds the machinery they all use. No ``__init__`` here imports
anything, so that the command line builds its ``--help`` without the seconds torch takes to import.
"""
