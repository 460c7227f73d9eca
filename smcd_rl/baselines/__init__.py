"""Baselines that are not a masked network plus a strategy: the oracle over physical parameters (O+P)
and the latent-variable model (LV+N)."""

from smcd_rl.baselines.latent import LatentVariableModel, fit_latent
from smcd_rl.baselines.oracle import OracleModel, ParameterFilter

__all__ = ["OracleModel", "ParameterFilter", "LatentVariableModel", "fit_latent"]
