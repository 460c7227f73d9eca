"""``smcd-rl two-link``: two-link arm look-ahead prediction (paper Fig. 2).

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
