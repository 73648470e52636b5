"""What crosses between nodes and runs: input filters, map arrays and their updates, checkpoints.
Imports the layers below."""
