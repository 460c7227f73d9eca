"""``smcd-rl bench filter``: one SMCD update against a dense matmul and a naive update.

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
