"""Self-collision settings (`SelfCollisionConfig`) and how they are recorded: read back from a
simulation file's metadata (`recorded_config`), put in a checkpoint's key (`key_settings`) and
changed from text (`with_settings`). Re-exported by `wrinkle_jax.sim.selfcollision`."""

from __future__ import annotations

import dataclasses

__all__ = ["ADDED_SETTINGS", "SelfCollisionConfig", "key_settings", "recorded_config",
           "with_settings"]


@dataclasses.dataclass(frozen=True)
class SelfCollisionConfig:
    """Static self-collision settings (hashable; nested in `xpbd.SimConfig`).

    Attributes:
      thickness: minimum vertex-triangle distance, m. Must stay well below the edge length
        (a flat sheet's non-adjacent vertex-triangle distances are >= ~0.8 PD).
      margin: extra search distance at a rebuild, m: must cover the relative motion of a
        vertex and a triangle between rebuilds (e.g. 3 m/s over one 1/600 s substep = 5 mm).
      rebuild_every: substeps between candidate rebuilds (1 = every substep).
      max_raw: hash-cell entries read per vertex. max_box: of those, triangles whose grown box
        holds the vertex that get the exact distance test. max_contacts: triangles kept.
      passes: Jacobi projection passes per substep before the body contacts.
      post_passes: passes after the body contacts, with the vertices the body moved held.
      rest_exclusion: m; a vertex and a triangle of its own panel whose rest (pattern)
        centroid lies closer than this are never candidates (0 = off). In a flat region
        these same-layer neighbours fill the candidate lists without ever becoming active;
        they can only touch through a crease sharper than the mesh resolves.
      pairs_per_vertex: the solver projects a flat list of at most ceil(this x V) contacts
        instead of V x max_contacts slots (0 = V x max_contacts, nothing dropped); contacts
        beyond it are counted in the overflow.
      raw_per_vertex: > 0 selects the flat build (`build_pairs`): the cell entries of all
        vertices are read into one list of ceil(this x V) slots (each vertex reads its whole
        cell, however full), instead of `max_raw` fixed slots per vertex; `max_raw`,
        `max_box` and `max_contacts` are then unused. box_per_vertex: the flat build's
        bound on triangles given the exact test, ceil(this x V). With the flat build every
        bound is a total, and where one overflows the nearest candidates are kept (the
        overflow is counted).
      block: > 0 (with raw_per_vertex > 0) selects the blocked flat build
        (`selfcollision_blocks.build_pairs_blocked`): the vertices of a cell are tested in
        blocks of this many against each cell entry, and `raw_per_vertex` bounds the
        (block, entry) slots at ceil(raw_per_vertex x V / block). Same contacts as the flat
        build when no bound is exceeded; the triangle data is gathered once per slot.
      poke_repair: > 0: a contact whose vertex has more than this fraction of its one-ring
        edges crossing the triangle (or its edge neighbours) is sent back to its ring's side
        (`pokethrough`); 0 = off, every contact keeps the vertex's start side.
      untangle: > 0: at every rebuild, each vertex of a face that crosses a contact's
        triangle (or a near face of its panel) moves this far (m) to shrink the
        intersection curves, and the contacts that name a crossed pair are dropped until the
        next rebuild (`untangle`); 0 = off. untangle_pairs: the bound
        on crossed face pairs it differentiates, ceil(this x V) (beyond: counted).
        untangle_smooth: rings around a curve its step is carried to.
      body_relax: rounds, after the body contacts (and the post passes), of one pass over
        the contacts with the cloth's own masses followed by the body contacts again
        (without friction); 0 = off. Where two layers lie pressed on the body, the body
        contact moves both to its surface and the post passes hold both (the vertices it
        moved), so their contact is frozen; a round lets the pair separate and the body
        then pushes the inner layer back out, so the outer one keeps the separation.
    """

    thickness: float = 0.004
    margin: float = 0.006
    rebuild_every: int = 1
    max_raw: int = 256
    max_contacts: int = 16
    max_box: int = 48
    passes: int = 1
    post_passes: int = 1
    rest_exclusion: float = 0.0
    pairs_per_vertex: float = 0.0
    raw_per_vertex: float = 0.0
    box_per_vertex: float = 8.0
    block: int = 0
    poke_repair: float = 0.0
    untangle: float = 0.0
    untangle_pairs: float = 0.25
    untangle_smooth: int = 0
    body_relax: int = 0


def recorded_config(recorded: dict | None) -> SelfCollisionConfig | None:
    """A simulation file's "self_collision" metadata (`dataclasses.asdict` of its config) as a
    config; None if it ran without. Settings added since the file was written take their
    defaults, which keep the old behaviour, so a new setting does not orphan stored files.
    Raises ValueError if it names a setting the config lacks."""
    if recorded is None:
        return None
    unknown = set(recorded) - {f.name for f in dataclasses.fields(SelfCollisionConfig)}
    if unknown:
        raise ValueError(f"self-collision settings {sorted(unknown)} are not SelfCollisionConfig's")
    return SelfCollisionConfig(**recorded)


# Settings added while the data set's regeneration was under way. Their defaults keep the
# behaviour before them (as `recorded_config` assumes), and at the default they are left out
# of a checkpoint's key (`key_settings`), so the runs' checkpoints stay valid.
ADDED_SETTINGS = ("body_relax",)


def key_settings(cfg: SelfCollisionConfig | None) -> dict | None:
    """`dataclasses.asdict(cfg)` without the `ADDED_SETTINGS` at their defaults (what a
    checkpoint's key records); None for None."""
    if cfg is None:
        return None
    default = SelfCollisionConfig()
    return {k: v for k, v in dataclasses.asdict(cfg).items()
            if k not in ADDED_SETTINGS or v != getattr(default, k)}


def with_settings(cfg: SelfCollisionConfig, text: str) -> SelfCollisionConfig:
    """cfg with the settings of "name=value[,name=value]" replaced (values typed by the field:
    e.g. "thickness=0.006,poke_repair=0.5"). Raises ValueError for an unknown name."""
    types = {f.name: f.type for f in dataclasses.fields(SelfCollisionConfig)}
    changes = {}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        if name not in types:
            raise ValueError(f"unknown self-collision setting {name!r} (of {sorted(types)})")
        changes[name] = int(value) if types[name] in (int, "int") else float(value)
    return dataclasses.replace(cfg, **changes)
