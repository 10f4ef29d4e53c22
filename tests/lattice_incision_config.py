"""The small incision fit configuration shared by the lattice-variant tests
(test_mesh_lattice_config.py, test_matched_lattice.py)."""


def incision_config(model, lam0=1.08, value=0.3):
    """A 2 mm cut through a 1 mm dermis (fitted) on 1 mm of fat, 6 x 4 mm, 1 mm cubes; the
    fitted parameter is ``pre_stretch``, the datum a max width of ``value`` mm."""
    e = {"name": "wound", "scenario": "incision", "model": model, "length_unit": "mm",
         "data": {"quantity": "max_width", "value": value},
         "specimen": {"size": [6, 4], "cells": [6, 4], "layers": [
             {"name": "dermis", "thickness": 1, "cells": 1, "fitted": True},
             {"name": "fat", "thickness": 1, "cells": 1, "youngs_modulus": 5e3, "poisson_ratio": 0.45}]},
         "cut": {"path": [[2, 2], [4, 2]], "depth": 1}, "scalpel_steps": 2}
    return {"material": {"youngs_modulus": 2e5, "poisson_ratio": 0.45, "pre_stretch": lam0},
            "fit": {"parameters": ["pre_stretch"]}, "experiment": [e]}
