"""fiberplan: collision-free motion planning for theta-phi fiber positioner robots."""
