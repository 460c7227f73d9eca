"""``smcd-rl interpret``: what the masks say: link lengths (Fig. 9), drone operators (Figs. 4, 13, 14).

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
