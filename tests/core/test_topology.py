"""Welding split vertices (bat3r_core.topology) against slow, obvious references; splitting and subdividing rigs."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from bat3r_core.rig import Rig
from bat3r_core.topology import split_rig, subdivide_rig, weld_rig, weld_vertices


def _slow_weld(v: np.ndarray, f: np.ndarray, tol: float):
    """Union-find over every pair closer than ``tol``; a component's representative is its lowest vertex, the
    components are numbered by the lexicographic (x, y, z) order of their representatives' positions."""
    parent = list(range(len(v)))

    def find(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for i in range(len(v)):
        for j in range(i + 1, len(v)):
            if np.linalg.norm(v[i] - v[j]) <= tol:
                parent[find(j)] = find(i)
    roots = [find(i) for i in range(len(v))]
    firsts = sorted({min(k for k in range(len(v)) if roots[k] == r) for r in set(roots)}, key=lambda k: tuple(v[k]))
    welded_of = np.array([firsts.index(min(k for k in range(len(v)) if roots[k] == roots[i])) for i in range(len(v))])
    pos = v[firsts]
    faces = [[welded_of[c] for c in face] for face in f]
    kept = [i for i, face in enumerate(faces) if len(set(face)) == 3]
    return welded_of, pos, np.array([faces[i] for i in kept]).reshape(-1, 3), np.array(kept), np.array(firsts)


def test_weld_vertices_matches_the_slow_reference():
    rng = np.random.default_rng(41)
    base = rng.uniform(-1, 1, (60, 3))
    # copies of some points, jittered well inside / well outside the tolerance (extent ~2 m -> tol ~2e-6 m)
    near = base[:25] + rng.normal(0, 1e-8, (25, 3))
    far = base[25:35] + rng.choice([-1, 1], (10, 3)) * 2e-5
    v = np.concatenate([base, near, far, base[:5]])[rng.permutation(100)]
    f = rng.integers(0, 100, (150, 3))
    w = weld_vertices(v, f)
    extent = np.ptp(v, axis=0).max()
    assert w.tolerance == pytest.approx(1e-6 * extent)
    ref_of, ref_pos, ref_faces, ref_kept, ref_first = _slow_weld(v, f, w.tolerance)
    np.testing.assert_array_equal(w.welded_of, ref_of)
    np.testing.assert_allclose(w.vertices, ref_pos, atol=1e-12)
    np.testing.assert_array_equal(w.faces, ref_faces)
    np.testing.assert_array_equal(w.face_source, ref_kept)
    np.testing.assert_array_equal(w.representative, ref_first)
    assert w.num_vertices == 70 and w.num_file_vertices == 100  # 25 near copies + 5 exact copies merged
    assert w.multiplicity.sum() == 100 and w.multiplicity.max() == 3
    assert not w.merges_nothing
    assert np.all(w.welded_of[w.representative] == np.arange(w.num_vertices))
    # an absolute tolerance large enough for the "far" copies merges them too
    assert weld_vertices(v, f, tolerance=1e-4).num_vertices == 60
    # zero tolerance merges exact duplicates only
    assert weld_vertices(v, f, relative_tolerance=0.0).num_vertices == 95


def test_weld_drops_degenerate_faces_and_maps_an_unindexed_mesh_back():
    s = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    soup = v[f.reshape(-1)]  # every triangle its own 3 vertices
    w = weld_vertices(soup, np.arange(len(soup)).reshape(-1, 3))
    assert w.num_vertices == len(v) and len(w.faces) == len(f)
    np.testing.assert_allclose(w.vertices[w.faces], v[f], atol=1e-12)  # same triangles, same order and winding
    np.testing.assert_allclose(soup, w.vertices[w.welded_of], atol=1e-12)
    assert trimesh.Trimesh(w.vertices, w.faces, process=False).is_watertight
    # a sliver whose two corners coincide becomes degenerate and is dropped; its source index is recorded
    f2 = np.concatenate([f, [[0, len(v), 1]]])
    v2 = np.concatenate([v, v[[0]] + 1e-9])
    w2 = weld_vertices(v2, f2)
    assert len(w2.faces) == len(f) and np.array_equal(w2.face_source, np.arange(len(f)))
    assert w2.num_file_faces == len(f) + 1 and not w2.merges_nothing
    same = weld_vertices(v, f)  # nothing to merge: a renumbering by position
    assert same.merges_nothing and sorted(same.welded_of) == list(range(len(v)))
    np.testing.assert_array_equal(same.vertices[same.welded_of], v)
    np.testing.assert_array_equal(same.faces, same.welded_of[f])
    assert np.all(np.diff(same.vertices[:, 0]) >= 0)
    # the welded mesh does not depend on the file's numbering: the unindexed soup welds to the same arrays
    np.testing.assert_array_equal(w.vertices, same.vertices)
    np.testing.assert_array_equal(w.faces, same.faces)


def test_weld_rig_averages_skin_weights_and_drops_uvs():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    w = np.array([[1, 0], [0.5, 0.5], [0.2, 0.8], [0.1, 0.9], [0, 1], [0.6, 0.4]])
    rest = np.tile(np.eye(4), (2, 1, 1))
    rest[1, :3, 3] = (1, 0, 0)
    rig = Rig(name="sheet", rest_vertices=v, faces=f, joint_names=("a", "b"), parents=np.array([-1, 0]),
              rest_transforms=rest, skin_weights=w, uvs=np.zeros((6, 2)))
    welded, welding = weld_rig(rig)
    # positions in lexicographic order: (0, 0), (0, 1), (1, 0), (1, 1)
    np.testing.assert_array_equal(welding.welded_of, [0, 2, 1, 2, 3, 1])
    np.testing.assert_array_equal(welded.faces, [[0, 2, 1], [2, 3, 1]])
    np.testing.assert_allclose(welded.skin_weights, [[1, 0], [0.4, 0.6], [0.3, 0.7], [0, 1]])
    np.testing.assert_allclose(welded.skin_weights.sum(1), 1.0)
    assert welded.uvs is None and welded.joint_names == rig.joint_names and welded.name == "sheet"
    np.testing.assert_array_equal(welded.rest_transforms, rig.rest_transforms)
    np.testing.assert_array_equal(welding.representative, [0, 2, 1, 4])


def test_weld_rejects_bad_arguments():
    v, f = np.zeros((4, 3)), np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match=r"vertices must have shape \(V, 3\)"):
        weld_vertices(np.zeros((4, 2)), f)
    with pytest.raises(ValueError, match="vertices must be finite"):
        weld_vertices(np.full((4, 3), np.nan), f)
    with pytest.raises(ValueError, match=r"faces index vertices outside \[0, 4\)"):
        weld_vertices(v, np.array([[0, 1, 4]]))
    with pytest.raises(ValueError, match="faces must be an integer array"):
        weld_vertices(v, np.array([[0.0, 1.0, 2.0]]))
    with pytest.raises(ValueError, match="relative_tolerance must be a finite number >= 0"):
        weld_vertices(v, f, relative_tolerance=-1e-6)
    with pytest.raises(ValueError, match="tolerance must be a finite number >= 0"):
        weld_vertices(v, f, tolerance=float("inf"))
    with pytest.raises(TypeError, match="rig must be a bat3r_core.rig.Rig"):
        weld_rig(v)


def test_split_rig_matches_the_slow_reference_and_welds_back(toy_rig):
    groups = toy_rig.skin_weights[toy_rig.faces].sum(1).argmax(1)  # faces by dominant bone: seams at bone borders
    split = split_rig(toy_rig, groups)
    # slow reference: one copy per (vertex, group) pair among the faces using the vertex
    copies = {(int(c), int(g)) for face, g in zip(toy_rig.faces, groups) for c in face}
    assert split.num_vertices == len(copies) > toy_rig.num_vertices
    np.testing.assert_array_equal(split.rest_vertices[split.faces], toy_rig.rest_vertices[toy_rig.faces])
    np.testing.assert_allclose(split.skin_weights[split.faces], toy_rig.skin_weights[toy_rig.faces], atol=1e-15)
    np.testing.assert_array_equal(split.uvs[split.faces], toy_rig.uvs[toy_rig.faces])
    for face, g, new in list(zip(toy_rig.faces, groups, split.faces))[::97]:
        for c, n in zip(face, new):  # every corner of a group uses that group's copy
            assert sorted(copies).index((int(c), int(g))) == n
    welded, welding = weld_rig(split)
    reference, ref_welding = weld_rig(toy_rig)
    np.testing.assert_array_equal(welded.rest_vertices, reference.rest_vertices)
    np.testing.assert_array_equal(welded.faces, reference.faces)
    np.testing.assert_allclose(welded.skin_weights, reference.skin_weights, atol=1e-12)
    np.testing.assert_array_equal(reference.rest_vertices[ref_welding.welded_of], toy_rig.rest_vertices)
    unindexed = split_rig(toy_rig, np.arange(len(toy_rig.faces)))
    assert unindexed.num_vertices == 3 * len(toy_rig.faces)
    with pytest.raises(ValueError, match=r"face_groups must be an integer array of shape \(F=9568,\)"):
        split_rig(toy_rig, groups[:5])


def test_subdivide_rig_keeps_the_surface_and_interpolates_weights():
    s = trimesh.creation.icosphere(subdivisions=1)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    rest = np.tile(np.eye(4), (2, 1, 1))
    w = np.stack([0.5 + 0.5 * v[:, 0], 0.5 - 0.5 * v[:, 0]], 1)
    rig = Rig(name="ball", rest_vertices=v, faces=f, joint_names=("a", "b"), parents=np.array([-1, 0]),
              rest_transforms=rest, skin_weights=w, uvs=v[:, :2])
    fine = subdivide_rig(rig)
    edges = trimesh.Trimesh(v, f, process=False).edges_unique
    assert fine.num_vertices == len(v) + len(edges) and len(fine.faces) == 4 * len(f)
    np.testing.assert_array_equal(fine.rest_vertices[:len(v)], v)
    for a, b in edges[::5]:  # every edge has a midpoint vertex with the mean weights of its ends
        k = np.flatnonzero(np.linalg.norm(fine.rest_vertices - 0.5 * (v[a] + v[b]), axis=1) < 1e-12)
        assert len(k) == 1
        np.testing.assert_allclose(fine.skin_weights[k[0]], 0.5 * (w[a] + w[b]))
        np.testing.assert_allclose(fine.uvs[k[0]], 0.5 * (v[a, :2] + v[b, :2]))
    m = trimesh.Trimesh(fine.rest_vertices, fine.faces, process=False)
    assert m.is_watertight and m.volume == pytest.approx(s.volume, rel=1e-9)  # same surface, same winding
