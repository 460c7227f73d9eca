"""``smcd-rl bench control``: the Panda reaching loop with SMCD, gradient descent and the analytic chain.

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
