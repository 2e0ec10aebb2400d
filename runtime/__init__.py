"""Per-frame runtime: frame types, physics conventions, configuration, stages, sinks.

This folder is the floor of the layering: it imports nothing from hw/, models/, calibration/ or the
entry package.
"""
