"""``hlbvh render`` as a hostile new user drives it, second round: a scene edited
between resumes, the scene's own integrator, frame entries that are not readable
files, bad face indices, Ctrl-C while rendering, unbounded clusters, schedulers that
never answer, and meshes, folders and files that used to end in a traceback. Every case
ends in complete frames only and, for a user error, one line naming what is wrong."""

import numpy as np
import pytest

from cli_helpers import interrupt_second_render, read_stats, run_cli, write_twist_scene
from hlbvh.render.output import LOCK_NAME

TINY = ["--triangles", "200", "--resolution", "16", "--spp", "1", "--quiet"]


def frames_of(directory):
    """The frames ``stats.json`` and ``stats.csv`` record (they must agree)."""
    document, table = read_stats(directory)
    rows = [row["frame"] for row in document["frames"]]
    assert rows == [int(row["frame"]) for row in table]
    return rows


# ---------------------------------------------------------------------------------------
# Ctrl-C while rendering
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("accel", ["hlbvh", "native"])
def test_ctrl_c_inside_mitsubas_render_stops_after_the_frame_and_resumes(
        tmp_path, capsys, monkeypatch, accel):
    """SIGINT raised inside ``mi.render`` (while Mitsuba's own handler is installed)
    stops the loop after that frame, exit 130; the same command renders the rest."""
    interrupt_second_render(monkeypatch)
    out = tmp_path / "out"
    argv = ["render", "cloth", "--frames", "0:4", "--accel", accel, "--out", out, *TINY]
    status, _, err = run_cli(capsys, *argv)
    assert status == 130 and err == ["hlbvh render: interrupted"], err
    assert frames_of(out) == [0, 1] and not (out / LOCK_NAME).exists()
    monkeypatch.undo()
    status, text, _ = run_cli(capsys, *argv)
    assert status == 0 and "2 rendered, 2 already complete" in text


# ---------------------------------------------------------------------------------------
# Frame files: every entry that looks like a frame is read or named; what Mitsuba's
# loader would misread or fail on is named with its frame and file
# ---------------------------------------------------------------------------------------


def ascii_ply(path, vertices, faces, index_type="int"):
    """An ASCII PLY of ``vertices`` (rows of x y z) and ``faces`` (rows of indices)."""
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}",
             "property float x", "property float y", "property float z",
             f"element face {len(faces)}", f"property list uchar {index_type} vertex_indices",
             "end_header"]
    lines += [" ".join(map(str, v)) for v in vertices]
    lines += [" ".join(map(str, [len(f), *f])) for f in faces]
    path.write_text("\n".join(lines) + "\n")


def binary_ply(path, vertices, faces):
    """A little-endian binary PLY with signed 32-bit indices."""
    vertices = np.asarray(vertices, dtype="<f4")
    rows = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rows["n"], rows["i"] = 3, faces
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\n"
              f"property float z\nelement face {len(faces)}\n"
              "property list uchar int vertex_indices\nend_header\n")
    path.write_bytes(header.encode() + vertices.tobytes() + rows.tobytes())


QUAD = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]


def break_frame(frames, case):
    """Make frame 1 (or, for links, a frame after the last) of shape ``bar`` what
    ``case`` names; returns the file the message must name."""
    bar = frames / "bar"
    second = bar / "frame_0002.ply"
    if case == "dangling link":
        (bar / "frame_0004.ply").symlink_to(bar / "gone.ply")
        return bar / "frame_0004.ply"
    if case == "looping link":
        (bar / "frame_0004.ply").symlink_to(bar / "frame_0004.ply")
        return bar / "frame_0004.ply"
    if case == "negative index, ascii":
        ascii_ply(second, QUAD, [(0, 1, 2), (0, 2, -1)])
    elif case == "negative index, binary":
        binary_ply(second, QUAD, [(0, 1, 2), (-1, 2, 3)])
    elif case == "face past the end":
        ascii_ply(second, QUAD, [(0, 1, 2), (0, 2, 9)])
    elif case == "no vertices":
        ascii_ply(second, [], [])
    elif case == "empty file":
        second.write_bytes(b"")
    elif case == "PLY named .obj":
        second.rename(bar / "frame_0002.obj")
        return bar / "frame_0002.obj"
    return second


@pytest.mark.parametrize("case, message", [
    ("dangling link", "a symbolic link that leads to no file (No such file or directory); "
                      "make it a readable mesh file or remove it"),
    ("looping link", "a symbolic link that leads to no file (Too many levels of symbolic "
                     "links); make it a readable mesh file or remove it"),
    ("negative index, ascii", "face 1 has vertex index -1; indices must be 0 or more"),
    ("negative index, binary", "face 1 has vertex index -1; indices must be 0 or more"),
    ("face past the end", "a face has vertex index 9, past its 4 vertices"),
    ("no vertices", "Mitsuba read 0 vertices and 0 faces from it; a frame needs at least "
                    "one triangle"),
    ("empty file", "the file is empty (0 bytes)"),
    ("PLY named .obj", "it holds PLY data but is named .obj; name it .ply"),
])
def test_frame_files_that_are_not_meshes_name_the_frame_and_file(tmp_path, capsys, case,
                                                                  message):
    xml, frames = write_twist_scene(tmp_path, triangles=100)
    named = break_frame(frames, case)
    out = tmp_path / "out"
    status, _, err = run_cli(capsys, "render", xml, "--frames-dir", frames, "--topology",
                             "changing", "--accel", "native", "--out", out, *TINY[2:])
    assert status == 2 and len(err) == 1, err
    if "link" in case:
        where = f"frame file {str(named)!r} of shape 'bar': "
    else:
        where = f"frame 1 of shape 'bar' ({str(named)!r}): "
    assert err[0] == f"hlbvh render: {where}{message}"
    assert not list(out.glob("frame_0001.*"))


def test_an_unreadable_frames_folder_and_scene_file_are_named(tmp_path, capsys, monkeypatch):
    """A folder that cannot be listed and a scene that cannot be read (as a user
    without root's override meets them) get one line each."""
    from pathlib import Path

    from hlbvh.scenes import sequence

    xml, frames = write_twist_scene(tmp_path, triangles=100)
    argv = ["render", xml, "--frames-dir", frames, "--out", tmp_path / "out", *TINY[2:]]
    real_iterdir, real_open = Path.iterdir, open

    def iterdir(self):
        if self == (frames / "bar").resolve():
            raise PermissionError(13, "Permission denied", str(self))
        return real_iterdir(self)

    monkeypatch.setattr(Path, "iterdir", iterdir)
    status, _, err = run_cli(capsys, *argv)
    assert status == 2 and err == [
        f"hlbvh render: frames directory {str((frames / 'bar').resolve())!r}: cannot be "
        f"listed (Permission denied)"], err
    monkeypatch.undo()

    def unreadable(name, *args, **kwargs):
        if Path(name) == xml:
            raise PermissionError(13, "Permission denied", str(name))
        return real_open(name, *args, **kwargs)

    monkeypatch.setattr(sequence, "open", unreadable, raising=False)
    status, _, err = run_cli(capsys, *argv)
    assert status == 2 and err == [
        f"hlbvh render: scene {str(xml)!r}: the file cannot be read (Permission denied)"], err


def test_apply_frame_takes_tensors_and_vectors_and_names_other_types():
    import mitsuba as mi

    from hlbvh import scenes
    from hlbvh.scenes import FrameGeometry, apply_frame

    animation = scenes.get("cloth", triangles=200)
    scene = mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=1))
    (shape, geometry), = animation.frame(3).items()
    flat = np.asarray(geometry.positions, dtype=np.float32).reshape(-1)
    for given in (mi.TensorXf(flat.reshape(-1, 3)), mi.Point3f(flat.reshape(-1, 3).T)):
        apply_frame(scene, None, {shape: FrameGeometry(given)})
        np.testing.assert_array_equal(np.asarray(mi.traverse(scene)[f"{shape}.vertex_positions"]),
                                      flat)
    with pytest.raises(ValueError) as raised:
        apply_frame(scene, None, {shape: FrameGeometry(flat.tolist())})
    assert str(raised.value) == (
        f"frame geometry for shape {shape!r}: positions of type list; expected a flat numpy "
        f"or Dr.Jit array (3 per entry), a tensor, or an array of 3-vectors")


# ---------------------------------------------------------------------------------------
# What the scene file decides: recorded, checked on resume, honoured
# ---------------------------------------------------------------------------------------

PATH_8 = '<integrator type="path"><integer name="max_depth" value="8"/></integrator>'


def edit(xml, old, new):
    text = xml.read_text()
    assert old in text
    xml.write_text(text.replace(old, new))


def test_a_scene_edited_between_resumes_is_refused_in_one_line(tmp_path, capsys):
    xml, frames = write_twist_scene(tmp_path, triangles=100)
    out = tmp_path / "out"
    argv = ["render", xml, "--frames-dir", frames, "--accel", "native", "--out", out, "--quiet"]
    assert run_cli(capsys, *argv, "--frames", "0:2")[0] == 0
    document, _ = read_stats(out)
    assert (document["settings"]["resolution"], document["settings"]["spp"]) == ([24, 16], 1)
    assert len(document["settings"]["scene_sha256"]) == 64
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    edit(xml, '"width" value="24"', '"width" value="32"')
    edit(xml, '"sample_count" value="1"', '"sample_count" value="4"')
    status, _, err = run_cli(capsys, *argv, "--frames", "0:3")
    assert status == 2 and err == [
        f"hlbvh render: {out} holds frames rendered with other settings (resolution: "
        f"[24, 16] -> [32, 16], scene_sha256: the scene file or a file it names was edited, "
        f"spp: 1 -> 4); choose another --out, or remove the directory to start over"], err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    # A file the scene includes, and a file it names (its mesh), each edited alone.
    edit(xml, '"width" value="32"', '"width" value="24"')
    edit(xml, '"sample_count" value="4"', '"sample_count" value="1"')
    edit(xml, '<emitter type="constant"/>', '<include filename="light.xml"/>')
    light = tmp_path / "light.xml"
    light.write_text('<scene version="3.0.0"><emitter type="constant"/></scene>')
    brighter = (b'<scene version="3.0.0"><emitter type="constant"><rgb name="radiance" '
                b'value="2"/></emitter></scene>')
    moved = (frames / "bar" / "frame_0002.ply").read_bytes()
    for k, (path, edited) in enumerate([(light, brighter), (tmp_path / "bar.ply", moved)]):
        again = tmp_path / f"again{k}"
        base = ["render", xml, "--frames-dir", frames, "--accel", "native", "--out", again,
                "--quiet"]
        assert run_cli(capsys, *base, "--frames", "0:1")[0] == 0
        original = path.read_bytes()
        path.write_bytes(edited)
        status, _, err = run_cli(capsys, *base, "--frames", "0:3")
        path.write_bytes(original)
        assert status == 2 and err == [
            f"hlbvh render: {again} holds frames rendered with other settings (scene_sha256: "
            f"the scene file or a file it names was edited); choose another --out, or remove "
            f"the directory to start over"], err


def test_the_scenes_own_integrator_is_honoured_and_a_flag_says_what_it_overrides(
        tmp_path, capsys):
    import mitsuba as mi

    from hlbvh.render import images

    xml, frames = write_twist_scene(tmp_path, triangles=100)
    edit(xml, PATH_8, '<integrator type="hlbvh_path"><string name="accel" value="native"/>'
                      '<integer name="max_depth" value="1"/></integrator>')
    out = tmp_path / "out"
    argv = ["render", xml, "--frames-dir", frames, "--frames", "0:1", "--quiet"]
    status, _, err = run_cli(capsys, *argv, "--out", out)
    assert status == 0 and err == [], err
    settings = read_stats(out)[0]["settings"]
    assert (settings["integrator"], settings["accel"], settings["max_depth"]) == ("path", "native", 1)
    ours = images.read_exr(out / "frame_0000.exr", ["R", "G", "B"])
    reference = np.asarray(mi.render(mi.load_file(str(xml)), seed=0))
    np.testing.assert_allclose(ours, reference, atol=1e-4)

    status, _, err = run_cli(capsys, *argv, "--max-depth", "3", "--accel", "hlbvh",
                             "--out", tmp_path / "flags")
    assert status == 0 and err == [
        "hlbvh render: the command line overrides the scene's integrator 'hlbvh_path': "
        "--max-depth 3 (the scene's max_depth: 1), --accel hlbvh (the scene's accel: "
        "'native')"], err
    settings = read_stats(tmp_path / "flags")[0]["settings"]
    assert (settings["accel"], settings["max_depth"]) == ("hlbvh", 3)

    edit(xml, '<integer name="max_depth" value="1"/></integrator>', '</integrator>')
    edit(xml, 'type="hlbvh_path"><string name="accel" value="native"/>', 'type="direct">')
    status, _, err = run_cli(capsys, *argv, "--out", tmp_path / "direct")
    assert status == 0 and err == [
        "hlbvh render: the scene's integrator 'direct' runs as hlbvh_direct (which mirrors "
        "it, every ray through the chosen accelerator)"], err
    edit(xml, 'type="direct">', 'type="ptracer">')
    status, _, err = run_cli(capsys, *argv, "--out", tmp_path / "ptracer")
    assert status == 2 and len(err) == 1 and err[0].startswith(
        f"hlbvh render: scene {str(xml)!r}: its integrator 'ptracer' is not one hlbvh render "
        f"runs ("), err
    status, _, err = run_cli(capsys, *argv, "--integrator", "aov", "--out", tmp_path / "aov")
    assert status == 0 and err == [
        "hlbvh render: --integrator aov overrides the scene's integrator 'ptracer' (its "
        "properties are not used)"], err


# ---------------------------------------------------------------------------------------
# Clusters: bounded by the machine; schedulers that do not speak Dask
# ---------------------------------------------------------------------------------------


def test_a_local_cluster_is_bounded_by_the_machine(tmp_path, capsys, monkeypatch):
    cluster = pytest.importorskip("hlbvh.render.cluster")
    argv = ["render", "cloth", "--frames", "0:2", "--out", tmp_path / "out", *TINY]
    status, _, err = run_cli(capsys, *argv, "--cluster", "local:100000")
    assert status == 2 and len(err) == 1 and "this machine runs at most" in err[0], err
    monkeypatch.setattr(cluster, "machine_capacity", lambda: (16, 3 * 2**30))
    status, _, err = run_cli(capsys, *argv, "--cluster", "local:7")
    assert status == 2 and err == [
        "hlbvh render: --cluster 'local:7': this machine runs at most 6 workers (16 cores, "
        "3.0 GiB free, 512 MiB a worker); use local:1 .. local:6, or --scheduler ADDRESS "
        "for more machines"], err
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


class Server:
    """A TCP server on 127.0.0.1 that does one of: accept and never send (``"silent"``),
    answer what it is sent with an HTTP error (``"http"``), greet with another
    protocol's banner (``"ssh"``)."""

    def __init__(self, kind):
        import socket
        import threading

        self.kind, self.socket = kind, socket.create_server(("127.0.0.1", 0))
        self.address = f"tcp://127.0.0.1:{self.socket.getsockname()[1]}"
        self.connections = []
        threading.Thread(target=self.serve, daemon=True).start()

    def serve(self):
        while True:
            try:
                connection, _ = self.socket.accept()
            except OSError:
                return
            self.connections.append(connection)
            if self.kind == "ssh":
                connection.sendall(b"SSH-2.0-OpenSSH_9.2\r\n")
            elif self.kind == "http" and connection.recv(1024):
                connection.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")

    def close(self):
        self.socket.close()
        for connection in self.connections:
            connection.close()


@pytest.mark.parametrize("kind, message", [
    ("silent", "something accepts connections there but sends nothing within 1 s, which a "
               "Dask scheduler does at once (another kind of server?); check the address"),
    ("http", "something accepts connections there but sends nothing within 1 s, which a "
             "Dask scheduler does at once (another kind of server?); check the address"),
    ("ssh", "what answers there is not a Dask scheduler (it began b'SSH-2.0-'); check the "
            "address"),
])
def test_a_scheduler_address_that_does_not_speak_dask_is_one_line(tmp_path, capsys,
                                                                   monkeypatch, kind, message):
    cluster = pytest.importorskip("hlbvh.render.cluster")
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", 1)
    server = Server(kind)
    try:
        status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:2", "--scheduler",
                                 server.address, "--out", tmp_path / "out", *TINY)
    finally:
        server.close()
    assert status == 2 and err == [f"hlbvh render: --scheduler {server.address}: {message}"], err


# ---------------------------------------------------------------------------------------
# Ctrl-C during start-up
# ---------------------------------------------------------------------------------------

STARTING = """
import signal, sys

class Interrupt:
    \"\"\"Ctrl-C as the command imports {module}.\"\"\"
    def find_spec(self, name, path, target=None):
        if name == {module!r}:
            signal.raise_signal(signal.SIGINT)
        return None

sys.meta_path.insert(0, Interrupt())
from hlbvh.cli.command import main
sys.exit(main(["render", "cloth", "--frames", "0:1", "--out", {out!r}]))
"""


@pytest.mark.parametrize("module", ["mitsuba", "hlbvh.cli.render"])
def test_ctrl_c_while_the_command_starts_is_one_line(tmp_path, module):
    """The console script (a file named ``hlbvh``) interrupted while it imports
    Mitsuba (the package) or a verb's module (the parser)."""
    import subprocess
    import sys

    script = tmp_path / "hlbvh"
    script.write_text(STARTING.format(module=module, out=str(tmp_path / "out")))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=120)
    assert (done.returncode, done.stderr) == (130, "hlbvh: interrupted\n")
    assert not (tmp_path / "out").exists()
