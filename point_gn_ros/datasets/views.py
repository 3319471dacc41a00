"""A dataset of simulated single-view scans: K views of every object of another dataset.

Item order: for source object s, the complete object first (if `include_full`), then views
0..K-1. `groups[i]` is the source object of item i and `view_index[i]` its view (-1 for the
complete object), so cross-validation can keep an object and its views in one fold.
"""

from __future__ import annotations

import numpy as np

from point_gn_ros.core.sampling import rotate_z
from point_gn_ros.core.views import (DEFAULT_VIEW_CONFIG, SIMULATOR_VERSION, ViewConfig,
                                     simulate_views)
from point_gn_ros.datasets.base import Dataset


class ViewsDataset(Dataset):
    """Seeded single-view scans of `base` (plus, optionally, its complete objects).

    views: K >= 0 scans per object; include_full: keep the complete object as well;
    random_yaw: turn every item by a seeded random angle about z after simulation (objects
    seen at any heading; with it, a bank without yaw alignment is a yaw-augmented bank);
    memoize: keep the simulated points in memory (encoding the same items twice is then free).
    Item i is deterministic in (seed, groups[i], view_index[i]) and the view configuration.
    """

    def __init__(self, base: Dataset, views: int, seed: int = 0,
                 cfg: ViewConfig | tuple[ViewConfig, ...] = DEFAULT_VIEW_CONFIG,
                 include_full: bool = True,
                 random_yaw: bool = False,
                 memoize: bool = False, sources: np.ndarray | None = None) -> None:
        if views < 0 or (views == 0 and not include_full):
            raise ValueError(f'views must be >= 1 (or >= 0 with include_full), got {views}')
        # cfg: one view configuration, or several sharing the K views in blocks (simulate_views)
        self.base, self.views, self.seed, self.cfg = base, views, seed, cfg
        cfgs = cfg if isinstance(cfg, tuple) else (cfg,)
        cfg_key = (sorted(cfgs[0].to_dict().items()) if len(cfgs) == 1
                   else [sorted(c.to_dict().items()) for c in cfgs])
        self.include_full, self.random_yaw = include_full, random_yaw
        # sources: (S,) int64 indices of the base objects used (default: all of them).
        self.sources = (np.arange(len(base), dtype=np.int64) if sources is None
                        else np.asarray(sources, dtype=np.int64))
        per = views + int(include_full)
        self.groups = np.repeat(self.sources, per)
        first = -1 if include_full else 0
        self.view_index = np.tile(np.arange(first, views, dtype=np.int64), len(self.sources))
        spec = (f'views={views},seed={seed},full={int(include_full)},'
                f'yaw={int(random_yaw)},cfg={cfg_key}')
        if views:
            spec += f',sim={SIMULATOR_VERSION}'
        if sources is not None:
            spec += f',sources={len(self.sources)}:{hash_seed(0, int(self.sources.sum()))}'
        labels = np.asarray(base.labels)[self.sources]
        super().__init__(base.path, f'{base.split}+{spec}', np.repeat(labels, per),
                         base.class_names)
        self.format = base.format
        self.skipped = list(getattr(base, 'skipped', []))
        self._memo: dict[int, list[np.ndarray]] | None = {} if memoize else None
        self._last: tuple[int, list[np.ndarray]] | None = None

    def describe(self) -> dict:
        """Provenance for bank metadata: what was simulated, from what, how."""
        return {'source_split': self.base.split, 'views_per_object': self.views,
                'include_full': self.include_full, 'random_yaw': self.random_yaw,
                'seed': self.seed,
                'view_config': ([c.to_dict() for c in self.cfg] if isinstance(self.cfg, tuple)
                                else self.cfg.to_dict()),
                'simulator_version': SIMULATOR_VERSION,
                'sources': int(len(self.sources))}

    def _items_of(self, source: int) -> list[np.ndarray]:
        """All items of one source object, in item order: list of (N_j, 3) float32."""
        if self._last is not None and self._last[0] == source:
            return self._last[1]
        if self._memo is not None and source in self._memo:
            return self._memo[source]
        xyz = self.base[source][0]
        items = [xyz] if self.include_full else []
        items += [v.points for v in simulate_views(xyz, self.views, hash_seed(self.seed, source),
                                                   self.cfg)] if self.views else []
        if self.random_yaw:
            rng = np.random.default_rng([self.seed, source, 0xA11])
            items = [rotate_z(p, a) for p, a in
                     zip(items, rng.uniform(0, 2 * np.pi, len(items)), strict=True)]
        self._last = (source, items)
        if self._memo is not None:
            self._memo[source] = items
        return items

    def _load(self, i: int) -> np.ndarray:
        per = self.views + int(self.include_full)
        return self._items_of(int(self.sources[i // per]))[i % per]


def hash_seed(seed: int, source: int) -> int:
    """One integer seed per (seed, source object): views of different objects are independent."""
    return int(np.random.default_rng([seed, source]).integers(2 ** 62))
