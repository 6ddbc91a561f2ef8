"""What both a robot agent and the server import: maps, target and sensor models, the episode
record, the wire contract (Zenoh keys, messages), the numpy belief filter, policy snapshots in
numpy, file helpers and the HTTP client. numpy, safetensors and the standard library only (zenoh is
imported lazily by ``wire.zenoh_config``): never torch, scipy, matplotlib or fastapi."""
