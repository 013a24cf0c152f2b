"""After the solve: the mover check, the tops of movers at pixel rows and the structure-from-motion baseline."""
