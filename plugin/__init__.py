"""hlbvh: HLBVH (Pantaleoni & Luebke, HPG 2010) as Dr.Jit kernels for Mitsuba 3.

``import hlbvh`` finds a libLLVM that Dr.Jit accepts (respecting DRJIT_LIBLLVM_PATH),
sets Mitsuba's variant when none is set yet (``cuda_ad_rgb`` where a GPU works,
``llvm_ad_rgb`` otherwise) and registers the integrators for it.
"""

from .environment import check_backend, ensure_llvm

ensure_llvm()

import drjit as _dr  # noqa: E402  (must follow ensure_llvm)
import mitsuba as _mi  # noqa: E402

check_backend()

if _mi.variant() is None:
    _mi.set_variant(
        "cuda_ad_rgb" if _dr.has_backend(_dr.JitBackend.CUDA) else "llvm_ad_rgb"
    )

from hlbvh.kernels.build import build  # noqa: E402
from hlbvh.kernels.bvh import BVH, BuildConfig, BuildStats  # noqa: E402
from hlbvh.accel import (NativeAccel, SceneAccel, ShapeParameters,  # noqa: E402
                         clear_camera_keys, clear_motion_keys, make_accel, set_camera_keys,
                         set_motion_keys, traverse)
from hlbvh.accel.keys import clear_instance_keys, set_instance_keys  # noqa: E402,F401
from hlbvh.integrators import register  # noqa: E402

register()

__all__ = ["build", "BVH", "BuildConfig", "BuildStats", "SceneAccel", "NativeAccel",
           "make_accel", "register", "traverse", "ShapeParameters", "set_motion_keys",
           "clear_motion_keys", "set_camera_keys", "clear_camera_keys"]
__version__ = "0.1.0"
