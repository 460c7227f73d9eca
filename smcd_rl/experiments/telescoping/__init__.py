"""``smcd-rl telescoping``: PD tracking with a telescoping link and adapted Jacobians (paper Fig. 8).

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
