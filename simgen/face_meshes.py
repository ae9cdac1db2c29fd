"""The meshes the renderer draws: every face coloured with the code of its index in the world's
face table, the static world cut into square tiles that are culled one by one, and depth-only
meshes for the shadow pass.
"""
from __future__ import annotations

import numpy as np

STATIC_TILE = 40.0   # metres: the side of the static world's culled tiles


def encode_ids(ids: np.ndarray) -> np.ndarray:
    """(n,) non-negative ints below 2^24 -> (n, 3) uint8 colours that carry them exactly."""
    ids = np.asarray(ids, dtype=np.int64)
    return np.stack([ids & 255, (ids >> 8) & 255, (ids >> 16) & 255], -1).astype(np.uint8)


def decode_ids(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 colours from :func:`encode_ids` -> (...) int64."""
    rgb = rgb.astype(np.int64)
    return rgb[..., 0] | (rgb[..., 1] << 8) | (rgb[..., 2] << 16)


def bounding_spheres(tiles: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Centre (n, 3) and radius (n,) of the bounding box's sphere of each (F, 3, 3) tile."""
    centre, radius = [], []
    for tile in tiles:
        lo, hi = tile.reshape(-1, 3).min(axis=0), tile.reshape(-1, 3).max(axis=0)
        centre.append((lo + hi) / 2)
        radius.append(float(np.linalg.norm(hi - lo)) / 2)
    return np.array(centre).reshape(-1, 3), np.array(radius)


def static_tiles(triangles: np.ndarray, size: float) -> list[np.ndarray]:
    """Split (F, 3, 3) triangles into square tiles of ``size`` metres by their centroid's x, y.

    Returns the face indices of each non-empty tile, tiles in (x, y) order, faces in their order.
    """
    cell = np.floor(triangles[:, :, :2].mean(axis=1) / size).astype(np.int64)
    cell -= cell.min(axis=0) if len(cell) else 0
    key = cell[:, 0] * (int(cell[:, 1].max(initial=0)) + 1) + cell[:, 1]
    order = np.argsort(key, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(key[order])) + 1)


def coded_mesh(pr, triangles: np.ndarray, first: int):
    """A pyrender mesh of (F, 3, 3) triangles, face f coloured with the code of index ``first + f``
    (:func:`encode_ids`), built as ``pyrender.Mesh.from_trimesh(..., smooth=False)`` builds a mesh
    with face colours (same material), less the normals the unlit pass does not read."""
    n = len(triangles)
    colours = np.full((n, 4), 255, np.uint8)
    colours[:, :3] = encode_ids(first + np.arange(n))
    material = pr.MetallicRoughnessMaterial(alphaMode="BLEND", baseColorFactor=[1.0, 1.0, 1.0, 1.0],
                                            metallicFactor=0.2, roughnessFactor=0.8)
    primitive = pr.Primitive(positions=triangles.reshape(-1, 3), color_0=np.repeat(colours, 3, axis=0),
                             material=material, mode=pr.constants.GLTF.TRIANGLES)
    return pr.Mesh(primitives=[primitive])


def depth_mesh(pr, triangles: np.ndarray):
    """A pyrender mesh of (F, 3, 3) triangles for depth-only passes (no colours, no normals)."""
    material = pr.MetallicRoughnessMaterial(baseColorFactor=[1.0, 1.0, 1.0, 1.0])
    return pr.Mesh(primitives=[pr.Primitive(positions=triangles.reshape(-1, 3), material=material,
                                            mode=pr.constants.GLTF.TRIANGLES)])
