"""One physical simulator for any chain: its terms (:mod:`.physics`), where arms settle
(:mod:`.equilibrium`), what a rig really is (:mod:`.truth`: the paper's planar arms and the
6-joint arm6 are two configurations), its files (:mod:`.rigs`)."""
