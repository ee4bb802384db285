"""Several datasets into one: the conflict check that must pass before anything is copied, then the copy."""

from __future__ import annotations

from pathlib import Path

from datagen.store import Dataset, StoreError, episode_key, shard_dir


def merge_datasets(sources: list[Dataset], out: str | Path, progress=None, tasks=None) -> Dataset:
    """Copy every episode of the `sources` datasets (of `tasks` only, if given: a list of task names) into
    OUT/shards/merged.zarr and return OUT as a Dataset.

    An episode key (datagen.store.episode_key) recorded with different content in two sources, or in a source
    and what OUT already holds (a merge continued, or more datasets added to it), is refused with a StoreError
    before anything is copied; identical copies are written once. `progress`, if given, is called once per
    source episode.
    """
    out = Path(out)
    if any(ds.root.resolve() == out.resolve() for ds in sources):
        raise StoreError(f"--out {out} is one of the sources: merge into a new directory")
    # what OUT already holds counts whole; the sources only with the tasks that will be copied
    there = [(f"--out {out}", Dataset(out), None)] if shard_dir(out).is_dir() else []
    owner: dict[tuple, tuple[str, str]] = {}  # episode key -> (where, content hash)
    for where, ds, only in there + [(str(ds.root), ds, tasks) for ds in sources]:
        for i in range(len(ds)):
            m = ds.meta(i)
            if only is not None and m["task"] not in only:
                continue
            key, h = episode_key(m), m["_sha256"]
            if key in owner and owner[key][1] != h:
                raise StoreError(f"episode {key} differs between {owner[key][0]} and {where}: merge datasets of "
                                 "different seeds, or leave one of them out")
            owner.setdefault(key, (where, h))
    for ds in sources:
        ds.merge(out, progress=progress, tasks=tasks)
    return Dataset(out)
