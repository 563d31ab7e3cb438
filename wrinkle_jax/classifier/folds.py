"""Cross-validation folds for the material classifiers: leave one GARMENT out (issue 25).

Several training scenes share a garment: the flared skirt dances in ``skirt_dance`` and
``skirt_dance2``, the apron in ``apron_dance`` and ``apron_dance2``. Leaving out one scene keeps
the same garment, in another motion, in training, so such a fold measures a garment the model
has already seen, while the held-out test is about unseen garments. `leave_one_garment_out`
therefore leaves out every scene of one garment at a time. The garment of a scene is read from
its definition (`wrinkle_jax.sim.scenes.SceneConfig.garment`, a key of
`wrinkle_jax.sim.patterns.GARMENTS`), never from its name.

Example:
    >>> from wrinkle_jax.classifier import folds
    >>> folds.scene_garments(["skirt_dance", "skirt_dance2", "apron_dance"])
    {'skirt_dance': 'flared_skirt', 'skirt_dance2': 'flared_skirt', 'apron_dance': 'apron'}
    >>> [f.validate for f in folds.leave_one_garment_out(["skirt_dance", "skirt_dance2",
    ...                                                   "apron_dance"])]
    [('apron_dance',), ('skirt_dance', 'skirt_dance2')]
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import NamedTuple

from wrinkle_jax.sim import scenes as sim_scenes


class Fold(NamedTuple):
    """One cross-validation fold: the left-out group (a garment, or a scene for
    `leave_one_scene_out`), the scenes fitted on and the scenes validated on."""

    group: str
    train: tuple[str, ...]
    validate: tuple[str, ...]


def scene_garments(scene_names: Iterable[str],
                   table: Mapping[str, sim_scenes.SceneConfig] | None = None) -> dict[str, str]:
    """Scene name -> garment, from the scene definitions.

    Args:
      scene_names: scene ids.
      table: name -> `SceneConfig` (default `wrinkle_jax.sim.scenes.SCENES`).

    Raises:
      SceneError: a name is not a defined scene.
    """
    table = sim_scenes.SCENES if table is None else table
    out = {}
    for name in scene_names:
        if name not in table:
            raise sim_scenes.SceneError(f"unknown scene {name!r}; expected one of "
                                        f"{', '.join(table)}")
        out[name] = table[name].garment
    return out


def garment_groups(scene_names: Iterable[str],
                   table: Mapping[str, sim_scenes.SceneConfig] | None = None
                   ) -> dict[str, tuple[str, ...]]:
    """Garment -> its scenes among `scene_names` (garments sorted by name, scenes in the
    given order)."""
    groups: dict[str, list[str]] = {}
    for name, garment in scene_garments(scene_names, table).items():
        groups.setdefault(garment, []).append(name)
    return {g: tuple(groups[g]) for g in sorted(groups)}


def _folds(groups: Mapping[str, tuple[str, ...]], names: list[str]) -> list[Fold]:
    out = []
    for g, held in groups.items():
        out.append(Fold(g, tuple(n for n in names if n not in held), tuple(held)))
    return out


def leave_one_garment_out(scene_names: Iterable[str],
                          table: Mapping[str, sim_scenes.SceneConfig] | None = None
                          ) -> list[Fold]:
    """One fold per garment: validate on all of its scenes, fit on the scenes of every other
    garment (so no fold has a garment on both sides). Folds in garment-name order."""
    names = list(dict.fromkeys(scene_names))
    return _folds(garment_groups(names, table), names)


def leave_one_scene_out(scene_names: Iterable[str]) -> list[Fold]:
    """One fold per scene (sessions 17-22's protocol; a garment of two scenes stays in
    training when one of them is left out). Folds in scene-name order."""
    names = list(dict.fromkeys(scene_names))
    return _folds({n: (n,) for n in sorted(names)}, names)
