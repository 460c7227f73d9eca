"""Baselines that are not a masked network plus a strategy (the oracle over physical parameters)."""

from smcd_rl.baselines.oracle import OracleModel, ParameterFilter

__all__ = ["OracleModel", "ParameterFilter"]
