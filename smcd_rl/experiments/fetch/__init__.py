"""``smcd-rl fetch``: Fetch task families with MPC on a learnt model.

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
