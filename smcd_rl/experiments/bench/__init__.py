"""``smcd-rl bench ...``: the benchmarks, one package per sub-command, and the config and tools they share."""
