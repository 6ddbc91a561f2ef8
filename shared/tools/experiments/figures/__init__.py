"""The paper's figures as experiments, one module per family; each figure function takes the run's
``Context`` and returns its results directory."""
