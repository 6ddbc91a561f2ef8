import json

import numpy as np
import pytest

from shared.core.models import ModelError, Sensor, from_matrix, lazy_walk, load_model_file, parse_target, uniform_walk


def test_uniform_walk_is_the_paper_target(small_graph):
    G = uniform_walk(small_graph).dense()
    assert np.allclose(G.sum(1), 1)
    assert G[small_graph.row(12), small_graph.row(13)] == pytest.approx(1 / 4)
    assert G[small_graph.row(14), small_graph.row(14)] == pytest.approx(1 / 2)
    assert not np.allclose(G, G.T)  # irregular degrees: orientation matters on this graph


def test_lazy_walk(small_graph):
    G = lazy_walk(small_graph, 0.9).dense()
    assert np.allclose(np.diag(G), 0.9)
    assert G[small_graph.row(12), small_graph.row(10)] == pytest.approx(0.1 / 3)
    with pytest.raises(ModelError):
        lazy_walk(small_graph, 1.5)


def test_matrix_validation_names_the_entry(small_graph):
    G = uniform_walk(small_graph).dense()
    bad = G.copy()
    bad[0, 4] = 0.1
    bad[0, 0] -= 0.1
    with pytest.raises(ModelError, match=r"gamma\[10\]\[14\].*not in the closed neighbourhood of 10"):
        from_matrix(small_graph, bad)
    bad = G.copy()
    bad[2, 2] += 0.5
    with pytest.raises(ModelError, match="row of node 12 sums to"):
        from_matrix(small_graph, bad)
    bad = G.copy()
    bad[1, 1] = -0.1
    with pytest.raises(ModelError, match="negative"):
        from_matrix(small_graph, bad)
    with pytest.raises(ModelError, match="5 x 5"):
        from_matrix(small_graph, G[:4, :4])


def test_model_file_round_trip_with_reordered_nodes(small_graph, tmp_path):
    m = lazy_walk(small_graph, 0.7, b0=np.array([0.5, 0.2, 0.1, 0.1, 0.1]))
    d = m.to_json(small_graph)
    order = [4, 2, 0, 3, 1]
    G = np.array(d["gamma"])
    rev = {
        "nodes": [d["nodes"][i] for i in order],
        "gamma": G[np.ix_(order, order)].tolist(),
        "b0": [d["b0"][i] for i in order],
    }
    p = tmp_path / "model.json"
    p.write_text(json.dumps(rev))
    back = load_model_file(small_graph, p)
    assert np.allclose(back.dense(), m.dense())
    assert np.allclose(back.b0, m.b0)
    assert np.allclose(parse_target(small_graph, str(p)).dense(), m.dense())


def test_sensor_bounds():
    with pytest.raises(ModelError, match="eta_fn"):
        Sensor(eta_fn=0.6)
    assert Sensor(eta_fn=0.5).likelihoods() == ((0.5, 0.5), (1.0, 0.0))  # the paper's largest eta_fn
    with pytest.raises(ModelError, match="uninformative"):
        Sensor(eta_fn=0.5, eta_fp=0.5)
    with pytest.raises(ModelError, match="detection"):
        Sensor(detection="cone")
    assert Sensor(0.1, 0.2).likelihoods() == ((0.1, 0.9), (0.8, 0.2))
