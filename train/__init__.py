"""Training scripts of the networks the package ships (run from the repository root:
``python -m train.semantic``)."""
