"""``smcd-rl ant``: crippled-leg Ant, planners x adaptations (paper appendix C, Fig. 15).

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
