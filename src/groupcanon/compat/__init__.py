"""Adapters from other equivariance libraries (optional extras): :mod:`groupcanon.compat.escnn`."""
