"""Validation support: measurements and reference models that check the product's answers.

Not reached by ``wrinkles run``; used by ``tests/``, ``benchmarks/`` and ``paper/``. It sits on
top of the layers (meshes -> models -> solvers) like the app, and the app does not import it.
"""
