"""One physical simulator for any chain: the physical terms (gravity, compliance, backlash and
play, servo non-linearity, encoder error, noise) in :mod:`.physics`, where arms settle in
:mod:`.equilibrium`, what a rig really is in :mod:`.truth` (the paper's planar arms and the
6-joint arm6 are two configurations of it), its files in :mod:`.rigs`."""
