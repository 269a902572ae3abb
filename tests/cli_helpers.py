"""What the command-line tests share: ``hlbvh`` run in this process, a render folder's
statistics as written, and a small XML scene whose animated mesh is read from PLY
frames (tests only)."""

from __future__ import annotations

import csv
import json
import shutil
import signal

from hlbvh import cli, scenes
from hlbvh.scenes.procedural import mesh_object


def run_cli(capsys, *argv):
    """``hlbvh argv`` in this process: (exit status, stdout, non-empty stderr lines)."""
    status = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, [line for line in err.splitlines() if line.strip()]


def interrupt_second_render(monkeypatch):
    """Raise SIGINT (Ctrl-C) inside the second ``sample`` call of ``hlbvh_path``, i.e.
    inside ``mi.render``, where Mitsuba's own handler is installed."""
    import mitsuba as mi

    # The class registered now (registering again, as other tests do, makes a new one).
    integrator = type(mi.load_dict({"type": "hlbvh_path"}))
    real, calls = integrator.sample, []

    def sample(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            signal.raise_signal(signal.SIGINT)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(integrator, "sample", sample)


def read_stats(directory) -> tuple[dict, list[dict]]:
    """A render folder's ``stats.json`` (the document) and ``stats.csv`` (its rows)."""
    document = json.loads((directory / "stats.json").read_text())
    with open(directory / "stats.csv", newline="") as f:
        return document, list(csv.DictReader(f))


_GROUP = """
  <shape type="shapegroup" id="grp"><shape type="sphere"><float name="radius" value="0.8"/></shape></shape>
  <shape type="instance" id="inst"><ref id="grp"/><transform name="to_world"><translate x="-1.5" y="1"/></transform></shape>"""


def write_twist_scene(root, triangles: int = 400, frames: int = 3, instances: bool = False):
    """A twisting bar (``frames`` PLY frames of about ``triangles``) over a floor, 24x16,
    box filter, ``path`` with max depth 8 (what ``hlbvh render`` renders); with
    ``instances`` also a shape group instanced once. Returns ``(scene.xml, frames dir)``."""
    twist = scenes.get("twist", triangles=triangles, frames=frames)
    faces = twist.parts["bar"].faces
    frames_dir = root / "frames" / "bar"
    frames_dir.mkdir(parents=True)
    for i in range(frames):
        positions = twist.frame(i)["bar"].positions.reshape(-1, 3)
        mesh_object("bar", positions, faces, {"type": "diffuse"}).write_ply(
            str(frames_dir / f"frame_{i + 1:04d}.ply"))
    shutil.copy(frames_dir / "frame_0001.ply", root / "bar.ply")
    (root / "scene.xml").write_text(f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="8"/></integrator>
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="4,2.5,6" target="0,1.5,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="16"/>
      <rfilter type="box"/></film>
    <sampler type="independent"><integer name="sample_count" value="1"/></sampler>
  </sensor>
  <shape type="ply" id="bar"><string name="filename" value="bar.ply"/></shape>{_GROUP if instances else ""}
  <shape type="rectangle" id="floor">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="10"/></transform></shape>
  <emitter type="constant"/>
</scene>""")
    return root / "scene.xml", root / "frames"
