"""``smcd-rl panda``: 7-DOF Panda reaching with an unknown tool (paper Fig. 3).

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
