"""The integrators hlbvh registers with Mitsuba: ``hlbvh_path``, ``hlbvh_direct``,
``hlbvh_volpath`` and ``hlbvh_prb`` (Mitsuba's ``path``, ``direct``, ``volpath`` and
``prb`` through an hlbvh intersector) and ``hlbvh_aov`` (primary-hit depth, shape,
primitive, normal and position)."""

import importlib
import sys

#: Modules of this package, ``common`` first: the others derive from its classes.
_MODULES = ("common", "path", "direct", "volpath", "aov", "prb")


def register():
    """Register every hlbvh integrator with Mitsuba for the current variant.

    Called by ``import hlbvh``; call it again after ``mi.set_variant(...)``. The
    integrator classes derive from the variant's ``mi.SamplingIntegrator``, so their
    modules are (re)loaded under the current variant, and each registers itself at
    its bottom.
    """
    for name in _MODULES:
        module = f"{__name__}.{name}"
        if module in sys.modules:
            importlib.reload(sys.modules[module])
        else:
            importlib.import_module(module)
