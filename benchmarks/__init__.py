"""Benchmarks of the product's path: each script prints a table and writes JSON under results/.

Installed with the project so that scripts, tests and the paper import each other's helpers as
``benchmarks.<name>`` without touching ``sys.path``.
"""
