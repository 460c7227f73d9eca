"""Integrations of smcd-rl with other libraries (torchrl, gymnasium); import each submodule explicitly."""
