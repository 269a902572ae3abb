"""Mitsuba's parse tree of a user's scene file, as :class:`hlbvh.scenes.SequenceScene`
edits it before the scene is built: the scene's relative paths resolved next to the
file, and every sensor's film size, samples per pixel and box filter set."""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi

from .animated import checked_resolution


class resolving_next_to:
    """Context in which Mitsuba's file resolver also looks next to an XML file (as
    ``mi.load_file`` does), so the scene's relative paths work."""

    def __init__(self, source):
        self._directory = source.parent if isinstance(source, Path) else None

    def __enter__(self):
        self._saved = mi.file_resolver()
        if self._directory is not None:
            resolver = mi.FileResolver(self._saved)
            resolver.prepend(str(self._directory))
            mi.set_file_resolver(resolver)

    def __exit__(self, *exc):
        mi.set_file_resolver(self._saved)


def configure_films(state, resolution, spp, box_filter: bool) -> None:
    """Sets size, samples per pixel and box filter on every sensor of a parse tree,
    adding the film, sampler or filter node a sensor leaves to its defaults.

    Nodes are addressed by index: appending to ``state.nodes`` may move them."""
    if resolution is not None:
        width, height = checked_resolution(resolution)
    if spp is not None and (not isinstance(spp, int) or isinstance(spp, bool) or spp < 1):
        raise ValueError(f"spp={spp!r}: expected a positive int")
    sensors = [k for k, node in enumerate(state.nodes) if node.type == mi.ObjectType.Sensor]
    for sensor in sensors:
        film = _child(state, sensor, mi.ObjectType.Film, "film", "hdrfilm")
        sampler = _child(state, sensor, mi.ObjectType.Sampler, "sampler", "independent")
        if resolution is not None:
            state.nodes[film].props["width"] = width
            state.nodes[film].props["height"] = height
        if spp is not None:
            state.nodes[sampler].props["sample_count"] = spp
        if box_filter:
            box = _add_node(state, mi.ObjectType.ReconstructionFilter, "box")
            props = state.nodes[film].props
            for name, value in list(props.items()):
                if (
                    isinstance(value, mi.Properties.ResolvedReference)
                    and state.nodes[value.index()].type == mi.ObjectType.ReconstructionFilter
                ):
                    del props[name]
            props["rfilter"] = box


def references(node) -> list[int]:
    """Indices of the nodes a parse-tree node refers to (its children)."""
    return [value.index() for _, value in node.props.items()
            if isinstance(value, mi.Properties.ResolvedReference)]


def _child(state, parent: int, kind, name: str, plugin: str) -> int:
    """Index of node ``parent``'s child of type ``kind``, added as ``plugin`` (under
    the property ``name``) when missing."""
    for _, value in state.nodes[parent].props.items():
        if (
            isinstance(value, mi.Properties.ResolvedReference)
            and state.nodes[value.index()].type == kind
        ):
            return value.index()
    reference = _add_node(state, kind, plugin)
    state.nodes[parent].props[name] = reference
    return reference.index()


def _add_node(state, kind, plugin: str) -> mi.Properties.ResolvedReference:
    """Appends a node of plugin ``plugin`` with default properties; its reference."""
    node = mi.parser.SceneNode()
    node.type = kind
    node.props = mi.Properties(plugin)
    state.nodes.append(node)
    return mi.Properties.ResolvedReference(len(state.nodes) - 1)
