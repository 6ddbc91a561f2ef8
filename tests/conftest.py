import numpy as np
import pytest

from shared.core.graph import Graph, graph_from_dict


@pytest.fixture
def small_graph() -> Graph:
    """5 nodes, a triangle with a tail and a pendant: irregular degrees, so Gamma != Gamma^T."""
    return graph_from_dict(
        {"name": "small", "nodes": [10, 11, 12, 13, 14], "edges": [[10, 11], [11, 12], [12, 10], [12, 13], [13, 14]]}
    )


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
