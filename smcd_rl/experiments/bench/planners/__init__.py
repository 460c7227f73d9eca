"""``smcd-rl bench planners``: our CEM against torchrl's CEMPlanner on the same model.

Its ``config`` imports no torch (``--help`` stays fast); ``run`` runs the command.
"""
