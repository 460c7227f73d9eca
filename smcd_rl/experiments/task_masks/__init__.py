"""``smcd-rl task-masks``: the task-mask network's training settings measured on each task family."""
