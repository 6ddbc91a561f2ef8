"""Worker for the data-parallel test: launched twice by torchrun (gloo, loopback)."""

import faulthandler
import json
import sys
from pathlib import Path

import torch
import torch.distributed as dist

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.learning.config import TrainConfig
from shared.learning.policy import TeamPolicy
from shared.learning.train import leave_process_group, train


def main() -> None:
    faulthandler.enable()  # an abort in torch's C++ (seen once in CI) then prints where Python was
    out = Path(sys.argv[1])
    dist.init_process_group("gloo")
    rank = dist.get_rank()
    g = builtin_graph("office")
    cfg = TrainConfig(robots=2, episodes=2048, batch=256, em_first=1024, em_every=10**9, em_missions=64, seed=4)
    if rank == 0:
        torch.manual_seed(cfg.seed)
        init = TeamPolicy(g.n, 2, torch.as_tensor(g.adjacency()))
        torch.save(dict(init.named_parameters()), out / "init.pt")
    res = train(g, uniform_walk(g), Sensor(), cfg)
    torch.save({k: v.detach() for k, v in res.policy.named_parameters()}, out / f"rank{rank}.pt")
    (out / f"rank{rank}.json").write_text(json.dumps({k: res.summary[k] for k in ("processes", "episodes")}))
    print(f"rank {rank}: wrote its weights", file=sys.stderr, flush=True)
    leave_process_group(0)  # as `mures train` leaves: no rank tears down while another still writes


if __name__ == "__main__":
    main()
