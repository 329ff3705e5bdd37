import numpy as np
import pytest
import torch

from torch_ampn.data import (
    MultiComponentMesh,
    NodeType,
    cells_to_edge_index,
    laminate_mesh,
    rectangle_mesh,
    stacked_plates,
)


def _signed_areas(pos: torch.Tensor, cells: torch.Tensor) -> np.ndarray:
    p = pos.double().numpy()[:, :2]
    c = cells.numpy()
    k = c.shape[1]
    # Shoelace formula, works for triangles and quads.
    x, y = p[c, 0], p[c, 1]
    return 0.5 * sum(x[:, i] * y[:, (i + 1) % k] - x[:, (i + 1) % k] * y[:, i] for i in range(k))


@pytest.mark.parametrize("cell_type", ["triangle", "quad"])
@pytest.mark.parametrize("nx,ny", [(1, 1), (3, 2), (7, 5)])
def test_rectangle_mesh_tiles_the_rectangle(cell_type, nx, ny):
    pos, cells = rectangle_mesh(nx, ny, size=(2.0, 3.0), origin=(1.0, -1.0, 0.5), cell_type=cell_type)
    assert pos.shape == ((nx + 1) * (ny + 1), 3)
    assert cells.shape == (
        (2 if cell_type == "triangle" else 1) * nx * ny,
        3 if cell_type == "triangle" else 4,
    )
    assert torch.allclose(pos.min(0).values, torch.tensor([1.0, -1.0, 0.5]))
    assert torch.allclose(pos.max(0).values, torch.tensor([3.0, 2.0, 0.5]))
    areas = _signed_areas(pos, cells)
    assert np.all(areas > 0), "cells must be counter-clockwise and non-degenerate"
    assert np.isclose(areas.sum(), 6.0)
    assert set(cells.unique().tolist()) == set(range(pos.size(0)))


def test_cells_to_edge_index_counts_match_grid_formula():
    nx, ny = 6, 4
    _, tri = rectangle_mesh(nx, ny)
    _, quad = rectangle_mesh(nx, ny, cell_type="quad")
    grid_edges = nx * (ny + 1) + ny * (nx + 1)
    ei_t, ei_q = cells_to_edge_index(tri), cells_to_edge_index(quad)
    assert ei_q.size(1) == 2 * grid_edges
    assert ei_t.size(1) == 2 * (grid_edges + nx * ny)  # plus one diagonal per square
    for ei in (ei_t, ei_q):
        pairs = set(map(tuple, ei.t().tolist()))
        assert len(pairs) == ei.size(1)  # no duplicates
        assert all((b, a) in pairs for a, b in pairs)  # both directions
        assert all(a != b for a, b in pairs)


def test_cells_to_edge_index_hand_computed_triangle_pair():
    cells = torch.tensor([[0, 1, 2], [1, 3, 2]])
    ei = cells_to_edge_index(cells)
    expected = {(0, 1), (1, 2), (0, 2), (1, 3), (2, 3)}
    expected |= {(b, a) for a, b in expected}
    assert set(map(tuple, ei.t().tolist())) == expected


def test_cells_to_edge_index_rejects_bad_input():
    with pytest.raises(ValueError, match="shape"):
        cells_to_edge_index(torch.zeros(4, dtype=torch.long))
    with pytest.raises(ValueError, match="integer"):
        cells_to_edge_index(torch.zeros(2, 3))
    with pytest.raises(ValueError, match="num_nodes"):
        cells_to_edge_index(torch.tensor([[0, 1, 5]]), num_nodes=3)


def test_stacked_plates_are_separate_components():
    m = stacked_plates(4, 3, num_layers=3, gap=0.5)
    n = 5 * 4
    assert m.num_nodes == 3 * n and m.num_components == 3
    assert torch.equal(m.component, torch.arange(3).repeat_interleave(n))
    ei = m.edge_index()
    assert torch.equal(m.component[ei[0]], m.component[ei[1]])
    assert torch.allclose(m.pos[m.component == 2, 2], torch.full((n,), 1.0))


def test_laminate_mesh_matches_paper_discretisation():
    m = laminate_mesh()
    assert m.names == ["ply0", "ply1", "ply2", "ply3", "punch", "die"]
    assert [c.size(0) for c in m.cells] == [3200] * 4 + [4290, 5100]
    assert m.num_nodes == 4 * 41 * 41 + 67 * 66 + 76 * 69
    assert (m.node_type[m.component < 4] == NodeType.PLY).all()
    assert (m.node_type[m.component == 4] == NodeType.PUNCH).all()
    assert (m.node_type[m.component == 5] == NodeType.DIE).all()
    z = [m.pos[m.component == c, 2].unique() for c in range(6)]
    assert all(t.numel() == 1 for t in z)
    assert torch.allclose(torch.cat(z), torch.tensor([0.0, 0.5, 1.0, 1.5, 2.0, -0.5]))
    assert laminate_mesh(scale=2).num_nodes == 4 * 81 * 81 + 133 * 131 + 151 * 137


def test_merge_rejects_empty_component():
    pos, cells = rectangle_mesh(1, 1)
    with pytest.raises(ValueError, match="'b' has no nodes"):
        MultiComponentMesh.merge([("a", pos, cells, NodeType.PLY), ("b", pos[:0], cells[:0], NodeType.DIE)])
