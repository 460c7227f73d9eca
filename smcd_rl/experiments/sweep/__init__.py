"""``smcd-rl sweep``: hyper-parameter ablations on Ray (paper Figs. 5, 6, 12).

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
