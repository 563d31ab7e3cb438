"""Cloth simulator (XPBD in JAX) and the scenes that make the training and test data.

Modules:
  patterns    2D sewing patterns meshed at a particle distance (PD) into seamed garments
  materials   the five fabrics (density, stretch, bending, damping, friction, thickness)
  colliders   spheres, capsules and planes with thickness and friction (JAX contact response)
  mannequin   procedural capsule body and its motions (kinematic tracks, NumPy)
  aero        aerodynamic drag/lift per triangle and a seeded gusty wind field
  xpbd        the solver: cloth model allocation (NumPy) and the (init_fn, step_fn) factory
  selfcollision  cloth-cloth contact: spatial-hash candidates, vertex-triangle thickness
              constraints (optional: `SimConfig.self_collision`)
  contact_scenes small layered scenes (two sheets, a folded strip) for self-collision
  scenes      frozen scene configs and `simulate`
  resume      checkpoints of a running simulation (a killed run resumes bit-identically)
  intersect   self-intersection measurement (spatial hash + exact triangle tests)
  preview     matplotlib previews (shaded frames, fine vs coarse normal maps)
  command     the `wrinkle-jax simulate` sub-command
"""
