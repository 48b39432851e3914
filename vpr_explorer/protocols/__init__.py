"""Evaluation protocols: the paper's splits, traversals, open set, the blocked fast path, sweeps, precision–recall, runs compared."""
