"""The paper's method: places (group/step), negative statistics, thresholds, retrieval and decisions."""
