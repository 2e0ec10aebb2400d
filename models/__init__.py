"""Learned illumination transfer: data generation, training (optional JAX extra), export to ONNX,
bundles of trained models, and evaluation. Stands on :mod:`illuminet.runtime`.
"""
