"""The character bundle: everything needed to pose and skin the MakeHuman character.

Contract:
  * `load_character()` reads everything once in NumPy (~1 s): the base mesh, its `body` and
    helper garments (`GARMENT_GROUPS`) as `MeshPart`s with the base-mesh vertex ids they came
    from, the skeleton (rest joints recomputed from the base mesh with the rig's placement
    rules, IK helpers added) and top-K weights.
  * `Character.part_weights(part)` gives a part's `SkinWeights`; `Character.walk_cycle(name)`
    loads a walk cycle retargeted to the skeleton.
  * Bad input raises `CharacterError` naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from wrinkle_jax.character.animation import Animation, load_walk_cycle
from wrinkle_jax.character.assets import CharacterError
from wrinkle_jax.character.mesh import BaseMesh, MeshPart, extract_part, load_base_mesh
from wrinkle_jax.character.rig import Skeleton, SkinWeights, load_skeleton, load_skin_weights

GARMENT_GROUPS = ("helper-skirt", "helper-tights")
BODY_GROUP = "body"
DEFAULT_RIG = "default"


@dataclasses.dataclass(frozen=True)
class Character:
    """Everything needed to pose and skin the MakeHuman character (NumPy arrays).

    Attributes:
      base: the full base mesh. skeleton: the rig (with IK helpers).
      weights: (N, K) top-K weights of every base-mesh vertex.
      body: the `body` group. garments: the helper garments, by group name.
      ground_height: lowest body z at rest (meters; the soles).
      asset_dir: folder the assets were read from. rig: the standard rig's name.
    """

    base: BaseMesh
    skeleton: Skeleton
    weights: SkinWeights
    body: MeshPart
    garments: dict[str, MeshPart]
    ground_height: float
    asset_dir: Path
    rig: str = DEFAULT_RIG

    def part_weights(self, part: MeshPart) -> SkinWeights:
        """Top-K weights of a part's vertices (K trimmed to what they use)."""
        return self.weights.subset(part.vertex_ids)

    def walk_cycle_paths(self) -> list[Path]:
        """The walk cycle json files shipped with the assets."""
        return sorted((self.asset_dir / "walkcycles").glob("*.json"))

    def walk_cycle(self, name: str | None = None, retarget: bool = True) -> Animation:
        """Load a walk cycle by file stem (default: the first one)."""
        paths = self.walk_cycle_paths()
        if not paths:
            raise CharacterError(f"{self.asset_dir}/walkcycles: no walk cycles")
        chosen = paths[0] if name is None else self.asset_dir / "walkcycles" / f"{name}.json"
        if not chosen.is_file():
            raise CharacterError(f"{chosen}: no such walk cycle; have "
                                 f"{[p.stem for p in paths]}")
        rig = self.asset_dir / "rigs" / "standard" / f"rig.{self.rig}.json"
        author = load_skeleton(rig, None, placement="default")
        return load_walk_cycle(chosen, self.skeleton, author, retarget)


def load_character(asset_dir: str | os.PathLike | None = None,
                   garments: Sequence[str] = GARMENT_GROUPS, rig: str = DEFAULT_RIG,
                   max_influences: int | None = None) -> Character:
    """Load the MakeHuman character (NumPy setup, ~1 s).

    Args:
      asset_dir: the fetched asset folder (default: `assets_fetch.makehuman_path()`, which
        raises with the command to run if the assets are missing).
      garments: helper groups to extract as garments.
      rig: standard rig name (rigs/standard/rig.<rig>.json and weights.<rig>.json).
      max_influences: top-K bones per vertex (default: all).
    """
    if asset_dir is None:
        from wrinkle_jax.assets_fetch import makehuman_path

        asset_dir = makehuman_path(required=True)
    asset_dir = Path(asset_dir)
    base = load_base_mesh(asset_dir / "3dobjs" / "base.obj")
    skel = load_skeleton(asset_dir / "rigs" / "standard" / f"rig.{rig}.json", base)
    weights = load_skin_weights(asset_dir / "rigs" / "standard" / f"weights.{rig}.json", skel,
                                base.mesh.num_vertices, max_influences)
    body = extract_part(base, BODY_GROUP, check_uvs=False)
    parts = {name: extract_part(base, name) for name in garments}
    ground = float(np.asarray(body.garment.vertices)[:, 2].min())
    return Character(base, skel, weights, body, parts, ground, asset_dir, rig)
