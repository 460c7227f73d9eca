"""What every experiment command shares: the harness, its torch-free base config, tuning, statistics, stages, outputs.

Nothing here knows any one command; a command's package imports from here, never the other way.
"""
