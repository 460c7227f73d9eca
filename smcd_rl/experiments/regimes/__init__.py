"""``smcd-rl regimes``: every adaptation method tuned by one criterion, scored in the regimes where each might win."""
