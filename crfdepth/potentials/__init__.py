"""The CRF's potentials: the data term with its occlusion gate and reweighting, the colour / normal /
3D-distance affinities, the learned head and the constrained weights (docs/design.md sections 3 and 4)."""
