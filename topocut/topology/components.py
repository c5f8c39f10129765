"""Connected components on the device: union-find with atomic hooking (Warp, CPU or CUDA).

Every element starts as a root (grid nodes: the first node of their run along
z, found by one thread per column).  Each edge (a, b) finds the roots of a and
b and hooks the larger root under the smaller one with a compare-and-swap that
only succeeds while it is still a root; when another thread hooked it first,
the loop goes on from its new root (ECL-CC, Jaiganesh & Burtscher 2018; with
Warp lacking atomic_cas, Playne & Hawick's 2018 atomic-min union).  Finding a
root points every visited element at its grandparent, which keeps the trees
shallow; a last pass points every element straight at its root.  Roots are
thus the *smallest index* of their component, and numbering the roots in index
order gives exactly the labels of scipy.ndimage.label (6-connected grid) and
scipy.sparse.csgraph.connected_components.  Exact after one pass over the
edges: no iteration to convergence, no host loop.

Grid elements are the nodes, flat index (i * ny + j) * nz + k; a node outside
the set has parent -1.  Pieces (``label_pieces``) are the components of one
union-find over the inside nodes *and* the marching-cubes vertices, linked by
grid edges, mesh edges and each vertex's inside node.
"""
# ruff: noqa: UP018  (int(0), float(...) declare mutable Warp kernel variables; a bare literal is a constant)
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from topocut.topology.sdf import init_warp


@wp.func
def find_root(parent: wp.array(dtype=wp.int32), a: int):
    # parents are never larger than their child; on the way up each visited element is pointed at
    # its grandparent (intermediate pointer jumping, ECL-CC), which keeps the trees shallow.  The
    # plain writes only touch non-roots and only ever store an ancestor, so they race harmlessly.
    curr = parent[a]
    if curr != a:
        prev = int(a)
        nxt = parent[curr]
        while curr > nxt:
            parent[prev] = nxt
            prev = curr
            curr = nxt
            nxt = parent[curr]
    return curr


@wp.func
def root_of(parent: wp.array(dtype=wp.int32), a: int):
    # the root without writing: for the last pass, where every element is pointed at its root.  find_root's
    # pointer jumping there would race with those writes: a thread that read an element's parent before the
    # element's own thread stored the root can store that older ancestor back over it (seen on CUDA: nodes left
    # pointing at a non-root, so unlabelled or counted under the wrong root)
    curr = a
    nxt = parent[curr]
    while nxt != curr:
        curr = nxt
        nxt = parent[curr]
    return curr


if hasattr(wp, "atomic_cas"):
    @wp.func
    def _hook(parent: wp.array(dtype=wp.int32), child: int, root: int):
        # the compare-and-swap only succeeds on a root: one another thread hooked first is left as it is
        return wp.atomic_cas(parent, child, child, root)
else:  # Warp without atomic_cas: Playne & Hawick's atomic-min union (may relink a non-root, then goes on)
    @wp.func
    def _hook(parent: wp.array(dtype=wp.int32), child: int, root: int):
        return wp.atomic_min(parent, child, root)


@wp.func
def unite(parent: wp.array(dtype=wp.int32), a0: int, b0: int):
    # hook the larger root under the smaller one (_hook returns the parent it found); a root that another
    # thread hooked first is followed up to its new root and tried again
    a = find_root(parent, a0)
    b = find_root(parent, b0)
    while a != b:
        if a < b:
            old = _hook(parent, b, a)
            if old == b:
                b = a
            else:
                b = find_root(parent, old)
        else:
            old = _hook(parent, a, b)
            if old == a:
                a = b
            else:
                a = find_root(parent, old)


@wp.func
def _member(v: float, inside: int):
    return (inside == 1 and v < 0.0) or (inside == 0 and v >= 0.0)


@wp.kernel
def _init_runs(field: wp.array3d(dtype=float), inside: int, parent: wp.array(dtype=wp.int32)):
    # one thread per z-column: each run of members along z points at its first element (its root),
    # so the unions below only have to join runs.  inside = 1: the set is {field < 0}; 0: {field >= 0}
    i, j = wp.tid()
    nz = field.shape[2]
    base = (i * field.shape[1] + j) * nz
    start = int(-1)
    for k in range(nz):
        if _member(field[i, j, k], inside):
            if start < 0:
                start = base + k
            parent[base + k] = start
        else:
            parent[base + k] = -1
            start = int(-1)


@wp.kernel
def _init_range(parent: wp.array(dtype=wp.int32), start: int):
    i = wp.tid() + start
    parent[i] = i


@wp.func
def _link_across(parent: wp.array(dtype=wp.int32), idx: int, k: int, d: int):
    # unite idx with its member neighbour idx - d, unless the elements below (k - 1) already link the
    # same two runs (idx - 1 and idx - 1 - d both members): then the runs are joined there
    if parent[idx - d] >= 0:
        implied = int(0)
        if k > 0:
            if parent[idx - 1] >= 0 and parent[idx - 1 - d] >= 0:
                implied = 1
        if implied == 0:
            unite(parent, idx, idx - d)


@wp.kernel
def _link_grid(parent: wp.array(dtype=wp.int32), ny: int, nz: int):
    # 6-connectivity: runs along z are joined already; join each to its member neighbours at -y and -x
    i, j, k = wp.tid()
    idx = (i * ny + j) * nz + k
    if parent[idx] < 0:
        return
    if j > 0:
        _link_across(parent, idx, k, nz)
    if i > 0:
        _link_across(parent, idx, k, ny * nz)


@wp.kernel
def _link_pairs(a: wp.array(dtype=wp.int32), b: wp.array(dtype=wp.int32), offset: int,
                parent: wp.array(dtype=wp.int32)):
    e = wp.tid()
    unite(parent, a[e] + offset, b[e] + offset)


@wp.kernel
def _link_faces(faces: wp.array(dtype=wp.int32), offset: int, parent: wp.array(dtype=wp.int32)):
    t = wp.tid()
    a = faces[3 * t] + offset
    unite(parent, a, faces[3 * t + 1] + offset)
    unite(parent, a, faces[3 * t + 2] + offset)


@wp.kernel
def _link_vertex_nodes(vnode: wp.array(dtype=wp.int32), offset: int, parent: wp.array(dtype=wp.int32)):
    v = wp.tid()
    node = vnode[v]
    if node >= 0:
        unite(parent, v + offset, node)


@wp.kernel
def _compress(parent: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if parent[i] >= 0:
        parent[i] = root_of(parent, i)


@wp.kernel
def _root_flags(parent: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    i = wp.tid()
    flags[i] = 0
    if parent[i] == i:
        flags[i] = 1


@wp.kernel
def _labels_of_roots(parent: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32),
                     scan: wp.array(dtype=wp.int32), labels: wp.array(dtype=wp.int32)):
    # scan: inclusive prefix sum of the kept-root flags -> label = scan[root] - 1; -1 outside or dropped
    i = wp.tid()
    p = parent[i]
    labels[i] = -1
    if p >= 0:
        if flags[p] == 1:
            labels[i] = scan[p] - 1


@wp.kernel
def _compress_mark_border(parent: wp.array(dtype=wp.int32), nx: int, ny: int, nz: int,
                          border: wp.array(dtype=wp.int32)):
    # compress, and flag the components that touch the grid border
    i, j, k = wp.tid()
    idx = (i * ny + j) * nz + k
    if parent[idx] < 0:
        return
    p = root_of(parent, idx)
    parent[idx] = p
    if i == 0 or j == 0 or k == 0 or i == nx - 1 or j == ny - 1 or k == nz - 1:
        border[p] = 1


@wp.kernel
def _count_enclosed(parent: wp.array(dtype=wp.int32), border: wp.array(dtype=wp.int32),
                    size: wp.array(dtype=wp.int32)):
    # the size of each component that does not touch the border: the air around the objects (one component, most
    # of the grid) is not counted, so its nodes do not all queue on one atomic counter
    i = wp.tid()
    p = parent[i]
    if p >= 0:
        if border[p] == 0:
            wp.atomic_add(size, p, 1)


@wp.kernel
def _fill_small_voids(field: wp.array3d(dtype=float), parent: wp.array(dtype=wp.int32),
                      size: wp.array(dtype=wp.int32), border: wp.array(dtype=wp.int32), max_voxels: int,
                      value: float):
    i, j, k = wp.tid()
    p = parent[(i * field.shape[1] + j) * field.shape[2] + k]
    if p >= 0:
        if border[p] == 0 and size[p] <= max_voxels:
            field[i, j, k] = value


@wp.kernel
def _compress_count(parent: wp.array(dtype=wp.int32), num_nodes: int, min_count: int,
                    count: wp.array(dtype=wp.int32)):
    # compress, and count the grid nodes (i < num_nodes) of each component up to min_count: only whether a
    # component reaches it is asked, and a large piece's nodes then stop queueing on its counter (a read that
    # comes late adds one more: the count only passes min_count by that)
    i = wp.tid()
    if parent[i] < 0:
        return
    p = root_of(parent, i)
    parent[i] = p
    if i < num_nodes:
        if count[p] < min_count:
            wp.atomic_add(count, p, 1)


@wp.kernel
def _kept_roots(parent: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), min_count: int,
                flags: wp.array(dtype=wp.int32)):
    i = wp.tid()
    flags[i] = 0
    if parent[i] == i and count[i] >= min_count:
        flags[i] = 1


def _number_roots(parent, flags, device):
    """Labels 0..K-1 for the roots flagged in ``flags``, in index order (K read back)."""
    scan = wp.empty_like(flags)
    wp.utils.array_scan(flags, scan, inclusive=True)
    labels = wp.empty_like(parent)
    wp.launch(_labels_of_roots, dim=parent.shape[0], inputs=[parent, flags, scan, labels], device=device)
    return int(scan[-1:].numpy()[0]), labels


def grid_union_find(field, inside: bool, device: str = "cpu", extra: int = 0):
    """Parent array (nx*ny*nz + extra,) of the 6-connected components of {field < 0} (inside) or {field >= 0}.

    The ``extra`` elements after the grid start as their own roots (for callers that link more).
    Call ``compress`` after the last link.
    """
    nx, ny, nz = field.shape
    parent = wp.empty(nx * ny * nz + extra, dtype=wp.int32, device=device)
    wp.launch(_init_runs, dim=(nx, ny), inputs=[field, int(inside), parent], device=device)
    if extra:
        wp.launch(_init_range, dim=extra, inputs=[parent, nx * ny * nz], device=device)
    wp.launch(_link_grid, dim=field.shape, inputs=[parent, ny, nz], device=device)
    return parent


def compress(parent, device: str = "cpu"):
    wp.launch(_compress, dim=parent.shape[0], inputs=[parent], device=device)
    return parent


def fill_voids(field, max_voxels: int, value: float, device: str = "cpu") -> None:
    """Fill enclosed outside regions of at most ``max_voxels`` nodes (gaps between jittered particles), in place.

    Outside nodes (field >= 0) not connected to the grid border are cavities;
    tiny ones are sampling artefacts that would become bubble shells in the
    mesh, large ones (a hollow object) are kept.
    """
    if max_voxels <= 0:
        return
    parent = grid_union_find(field, inside=False, device=device)
    size = wp.zeros(parent.shape[0], dtype=wp.int32, device=device)
    border = wp.zeros(parent.shape[0], dtype=wp.int32, device=device)
    wp.launch(_compress_mark_border, dim=field.shape, inputs=[parent, *field.shape, border], device=device)
    wp.launch(_count_enclosed, dim=parent.shape[0], inputs=[parent, border, size], device=device)
    wp.launch(_fill_small_voids, dim=field.shape,
              inputs=[field, parent, size, border, int(max_voxels), float(value)], device=device)


@dataclass
class Pieces:
    count: int  # K kept pieces
    labels: object  # warp int32 (G + V,): piece 0..K-1 of each grid node / mesh vertex, -1 outside or dropped
    num_nodes: int  # G: vertex v is element G + v


def label_pieces(field, faces, vnode, num_verts: int, min_voxels: int, device: str = "cpu") -> Pieces:
    """Pieces = components of {inside nodes (6-connected)} + {mesh vertices (mesh edges)} + {vertex -- its inside node}.

    faces: warp int32 (3F,) flat; vnode: warp int32 (V,), the inside node of
    each vertex's grid edge (-1 none).  Pieces with fewer than ``min_voxels``
    inside nodes are dropped (debris).  Piece ids follow the smallest member index.
    """
    init_warp()
    g = int(np.prod(field.shape))
    parent = grid_union_find(field, inside=True, device=device, extra=num_verts)
    if num_verts:
        wp.launch(_link_faces, dim=faces.shape[0] // 3, inputs=[faces, g, parent], device=device)
        wp.launch(_link_vertex_nodes, dim=num_verts, inputs=[vnode, g, parent], device=device)
    count = wp.zeros(g + num_verts, dtype=wp.int32, device=device)  # inside nodes per root, up to min_voxels
    min_count = max(int(min_voxels), 1)
    wp.launch(_compress_count, dim=g + num_verts, inputs=[parent, g, min_count, count], device=device)
    flags = wp.empty_like(parent)
    wp.launch(_kept_roots, dim=parent.shape[0], inputs=[parent, count, min_count, flags], device=device)
    k, labels = _number_roots(parent, flags, device)
    return Pieces(k, labels, g)


# -- host entry points (tests, small graphs) -------------------------------------------------------

def graph_components(edges, num_nodes: int, device: str = "cpu") -> tuple[int, np.ndarray]:
    """Connected components of an undirected graph: (count, labels (n,)), labels as scipy's connected_components."""
    init_warp()
    e = np.asarray(edges, np.int32).reshape(-1, 2)
    parent = wp.array(np.arange(num_nodes, dtype=np.int32), dtype=wp.int32, device=device)
    if len(e):
        a = wp.array(np.ascontiguousarray(e[:, 0]), dtype=wp.int32, device=device)
        b = wp.array(np.ascontiguousarray(e[:, 1]), dtype=wp.int32, device=device)
        wp.launch(_link_pairs, dim=len(e), inputs=[a, b, 0, parent], device=device)
    compress(parent, device)
    flags = wp.empty_like(parent)
    wp.launch(_root_flags, dim=num_nodes, inputs=[parent, flags], device=device)
    k, labels = _number_roots(parent, flags, device)
    return k, labels.numpy()


def grid_components(mask, device: str = "cpu") -> tuple[np.ndarray, int]:
    """6-connected components of a boolean 3D mask: (labels (nx,ny,nz), count) as scipy.ndimage.label."""
    init_warp()
    field = wp.array(np.where(np.asarray(mask, bool), -1.0, 1.0).astype(np.float32), dtype=float, device=device)
    parent = compress(grid_union_find(field, inside=True, device=device), device)
    flags = wp.empty_like(parent)
    wp.launch(_root_flags, dim=parent.shape[0], inputs=[parent, flags], device=device)
    k, labels = _number_roots(parent, flags, device)
    return labels.numpy().reshape(field.shape) + 1, k
