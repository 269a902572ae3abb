"""The scene accelerator: a Mitsuba scene's ray queries over the groups that trace its
shapes (the still world in a Mitsuba sub-scene, moving meshes in our BVHs, moving
instances under our top level), the motion that decides what each frame updates, the
update policy, and :func:`traverse` for an animation loop that skips Mitsuba's rebuild.

Modules: ``scene_accel`` (:class:`SceneAccel`), ``native_group``, ``mesh_group``,
``instance_group`` (the groups), ``instance_shading`` (hits inside instances expanded),
``motion`` (which shapes moved), ``scene_geometry`` (which shapes are meshes, analytic or
traced still), ``queries`` (``mi.Scene``'s query signatures, :class:`NativeAccel`),
``policy`` (the options and :class:`UpdatePolicy`), ``parameters`` (:func:`traverse`),
``keys`` (:func:`set_motion_keys`, :func:`set_camera_keys`: a mesh's positions and
a camera's poses over the shutter) and
``keyed_shading`` (a hit shaded where its mesh is at the ray's time).
"""

from hlbvh.accel.keys import (clear_camera_keys, clear_motion_keys, set_camera_keys,
                              set_motion_keys)
from hlbvh.accel.parameters import ShapeParameters, traverse
from hlbvh.accel.queries import NativeAccel
from hlbvh.accel.scene_accel import SceneAccel, make_accel

__all__ = ["SceneAccel", "NativeAccel", "make_accel", "traverse", "ShapeParameters",
           "set_motion_keys", "clear_motion_keys", "set_camera_keys", "clear_camera_keys"]
