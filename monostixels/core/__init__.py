"""The model and its solver: geometry, classes, the energy, per-column costs, the DP (and its C++ kernel) and the stixel world."""
