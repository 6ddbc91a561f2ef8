"""CE-PG learning in torch: the stacked per-robot policy networks, the CE-PG rollout and loss
(Eq. 9-13), the training loop (Algorithm 2) and snapshots as torch modules. Imports shared.core and
shared.engine."""
