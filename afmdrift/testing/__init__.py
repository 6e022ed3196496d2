"""Helpers for tests, demos and benchmarks: synthetic textures and exact shifts.

Runtime code (the service) never imports this package.
"""
