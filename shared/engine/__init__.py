"""The simulation engine in torch: batched beliefs, the batched simulator of the paper setup, the
reference searchers, evaluation with capture-time statistics, and EM estimation of the target
model. Imports shared.core only."""
