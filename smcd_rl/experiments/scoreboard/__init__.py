"""``smcd-rl scoreboard``: one table and plot of every task from experiments' run directories.

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
