"""One physical simulator for any chain: the physics (gravity, compliance, backlash and play,
servo non-linearity, encoder error, noise) in :mod:`.physics`, where arms settle in
:mod:`.equilibrium`, what a rig really is in :mod:`.truth`, its files in :mod:`.rigs`.

The paper's planar setup (:func:`paper_truth`) and the 6-joint arm6 (:class:`ChainTruth`,
:class:`LinkedChainTruth`) are two configurations of it.
"""

from bayesrob.sim.equilibrium import (
    LinkedEquilibrium,
    LinkedSimulationError,
    PhysicalRig,
    commanded_angles,
    linked_energy,
    linked_equilibrium,
    position_ik,
)
from bayesrob.sim.physics import (
    draw_stiffnesses,
    encoder_error,
    gravity_deflection,
    gravity_torques,
    play_offsets,
)
from bayesrob.sim.rigs import (
    grid_points,
    holdout_points,
    holdout_seed,
    measure_planned,
    nominal_specs,
    random_poses,
    round_pulse,
    simulate_chain_rig,
    simulate_linked_chain_rig,
    simulate_rig,
    true_parameters,
    write_arm6_rig,
)
from bayesrob.sim.truth import (
    GRAVITY,
    LINKED_ARMS,
    POSE_HI,
    POSE_LO,
    THIRD_ARM,
    THIRD_ARM_STIFFNESS_SCALE,
    TRUTH_FILE,
    ArmTruth,
    ChainTruth,
    LinkedChainTruth,
    Truth,
    arm6_urdf_path,
    drawn_masses,
    drawn_stiffness,
    load_linked_truth,
    load_true_params,
    paper_truth,
    three_arm_truth,
    three_linked_chain_truth,
    with_drawn_stiffness,
)

__all__ = [
    "GRAVITY", "LINKED_ARMS", "POSE_HI", "POSE_LO", "THIRD_ARM", "THIRD_ARM_STIFFNESS_SCALE",
    "TRUTH_FILE", "arm6_urdf_path", "ArmTruth", "ChainTruth", "commanded_angles",
    "draw_stiffnesses", "drawn_masses", "drawn_stiffness", "encoder_error", "gravity_deflection",
    "gravity_torques", "grid_points", "holdout_points", "holdout_seed", "linked_energy",
    "linked_equilibrium", "LinkedChainTruth", "LinkedEquilibrium", "LinkedSimulationError",
    "load_linked_truth", "load_true_params", "measure_planned", "nominal_specs", "paper_truth",
    "PhysicalRig", "play_offsets", "position_ik", "random_poses", "round_pulse",
    "simulate_chain_rig", "simulate_linked_chain_rig", "simulate_rig", "three_arm_truth",
    "three_linked_chain_truth", "true_parameters", "Truth", "with_drawn_stiffness",
    "write_arm6_rig",
]
