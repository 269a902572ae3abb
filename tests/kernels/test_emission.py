"""The partial breadth-first hierarchy emission against trees written by hand and
against the definition of the tree, written as the obvious recursion."""

import hashlib
import os
import pathlib
import subprocess
import sys

import drjit as dr
import numpy as np
import pytest

import hlbvh  # noqa: F401  (sets up Dr.Jit)
import mitsuba as mi
from hlbvh.kernels.arrays import namespace_of
from hlbvh.kernels.emission import NodeRecords, emit_hierarchy
from meshes import KEY_KINDS, random_sorted_keys


def emitted_tree(keys, key_bits, leaf_size, p):
    """Emit over the whole key array; return the set of (lo, hi, is_leaf) node ranges,
    after checking that node numbering puts siblings next to each other."""
    ns = namespace_of(mi.UInt32(0))
    Key = ns.UInt64 if key_bits > 32 else ns.UInt32
    n = len(keys)
    cap = max(2 * n - 1, 1)
    U = ns.UInt32
    rec = NodeRecords(*(dr.zeros(U, cap) for _ in range(3)), total=U(1))
    roots = (U([0]), U([n]), U([0]), U([0]))
    emit_hierarchy(Key(np.asarray(keys)), key_bits, 0, roots, rec, leaf_size, p)
    total = int(rec.total[0])
    first = rec.first.numpy()[:total]
    count = rec.count.numpy()[:total]
    depth = rec.depth.numpy()[:total]
    out = []

    def walk(node, d):
        assert depth[node] == d
        if count[node]:
            out.append((int(first[node]), int(first[node] + count[node]), True))
            return int(first[node]), int(first[node] + count[node])
        c = int(first[node])
        assert c > node
        a, m = walk(c, d + 1)
        m2, b = walk(c + 1, d + 1)
        assert m == m2, "children ranges must be adjacent"
        out.append((a, b, False))
        return a, b

    assert walk(0, 0) == (0, n)
    assert len(out) == total, "every allocated node is in the tree"
    return sorted(out)


def definition_tree(keys, key_bits, leaf_size):
    """The tree by definition: a range of more than leaf_size primitives splits at the
    first bit plane where its keys differ (before the first key with a 1 there); a
    range of identical keys splits at its middle index."""
    keys = [int(k) for k in keys]
    out = []

    def rec(lo, hi, plane):
        if hi - lo <= leaf_size:
            out.append((lo, hi, True))
            return
        while plane < key_bits:
            bits = [(k >> (key_bits - 1 - plane)) & 1 for k in keys[lo:hi]]
            if bits[0] != bits[-1]:
                split = lo + bits.index(1)
                out.append((lo, hi, False))
                rec(lo, split, plane + 1)
                rec(split, hi, plane + 1)
                return
            plane += 1
        mid = (lo + hi) // 2
        out.append((lo, hi, False))
        rec(lo, mid, plane)
        rec(mid, hi, plane)

    rec(0, len(keys), 0)
    return sorted(out)


HAND_KEYS = [0b0000, 0b0001, 0b0100, 0b0110, 0b1000, 0b1000, 0b1111]


@pytest.mark.parametrize("p", [1, 2, 3, 5])
def test01_hand_made_tree_leaf_size_1(p):
    # Plane 0 splits at 4 (first key 1xxx); [0,4) at plane 1 splits at 2; [0,2) passes
    # plane 2 and splits at plane 3; [2,4) splits at plane 2; [4,7) splits at plane 1
    # at 6; [4,6) holds two equal keys and is split at its middle.
    expected = sorted([
        (0, 7, False), (0, 4, False), (0, 2, False), (0, 1, True), (1, 2, True),
        (2, 4, False), (2, 3, True), (3, 4, True), (4, 7, False), (4, 6, False),
        (4, 5, True), (5, 6, True), (6, 7, True),
    ])
    assert emitted_tree(HAND_KEYS, 4, 1, p) == expected


@pytest.mark.parametrize("p", [1, 3])
def test02_hand_made_tree_leaf_size_2(p):
    expected = sorted([
        (0, 7, False), (0, 4, False), (0, 2, True), (2, 4, True),
        (4, 7, False), (4, 6, True), (6, 7, True),
    ])
    assert emitted_tree(HAND_KEYS, 4, 2, p) == expected


def test03_identical_keys_split_at_the_middle():
    expected = sorted([
        (0, 5, False), (0, 2, False), (0, 1, True), (1, 2, True),
        (2, 5, False), (2, 3, True), (3, 5, False), (3, 4, True), (4, 5, True),
    ])
    assert emitted_tree([7] * 5, 4, 1, 3) == expected


def test04_single_primitive_is_a_leaf():
    assert emitted_tree([3], 30, 4, 3) == [(0, 1, True)]


@pytest.mark.parametrize("key_bits", [30, 60])
@pytest.mark.parametrize("kind", KEY_KINDS)
def test05_random_keys_match_the_definition(key_bits, kind):
    for keys in random_sorted_keys(key_bits, kind):
        for leaf_size in (1, 4):
            for p in (2, 3):
                assert emitted_tree(keys, key_bits, leaf_size, p) == definition_tree(
                    keys, key_bits, leaf_size
                )


_DIGEST = """
import hashlib, meshes
h = hashlib.sha256()
for bits in (30, 60):
    for kind in meshes.KEY_KINDS:
        for keys in meshes.random_sorted_keys(bits, kind):
            h.update(keys.tobytes())
print(h.hexdigest())
"""


def test06_random_keys_are_the_same_in_every_process():
    """test05's keys do not depend on the process (Python salts string hashes per
    process: a seed from ``hash()`` would test other keys each run, and a failure could
    not be replayed)."""
    here = pathlib.Path(__file__).resolve().parents[1]  # tests/
    digests = {
        subprocess.run([sys.executable, "-c", _DIGEST], cwd=here, check=True, text=True,
                       capture_output=True,
                       env=dict(os.environ, PYTHONHASHSEED=str(salt))).stdout.strip()
        for salt in (1, 2)
    }
    expected = hashlib.sha256()
    for bits in (30, 60):
        for kind in KEY_KINDS:
            for keys in random_sorted_keys(bits, kind):
                expected.update(keys.tobytes())
    assert digests == {expected.hexdigest()}
