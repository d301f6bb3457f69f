"""Keys renamed since checkpoints were written: old checkpoints hold the old names, which
`runs.checkpoint.Checkpointer.restore_items` maps (`has_legacy_keys` on the stored tree, then
restore into `to_legacy(template)` and return `from_legacy(restored)`)."""

from __future__ import annotations

import re
from typing import Any

LEGACY_GROUP_NAMES = (("frozen", "no_update"),)
"""(old, new) optimizer group names (new: `train.state.NO_UPDATE`): the optimizer state keys
its per-group states by group (``opt_state.inner_states``), so a checkpoint written before a
rename holds the old name; renamed when it is restored."""

LEGACY_KEYS: tuple[tuple[str, str, str | None], ...] = (
    *((old, new, "inner_states") for old, new in LEGACY_GROUP_NAMES),
)
"""(old, new, parent) key names of checkpoints written before a rename: a key of any item's tree
(``{i}``: digits), where `parent` (when not None) is the key holding it. `Checkpointer.restore_items`
restores such a checkpoint under its old names and returns the trees under the new ones."""


def _key_pattern(name: str) -> re.Pattern:
    return re.compile(re.escape(name).replace(re.escape("{i}"), r"(\d+)"))


_LEGACY = [(_key_pattern(old), old, _key_pattern(new), new, parent)
           for old, new, parent in LEGACY_KEYS]


def _renamed(key: Any, parent: Any, to_new: bool) -> Any:
    """`key` under its new name (`to_new`) or its old one, per `LEGACY_KEYS`."""
    if not isinstance(key, str):
        return key
    for old_re, old, new_re, new, where in _LEGACY:
        match = (old_re if to_new else new_re).fullmatch(key)
        if match and where in (None, parent):
            return (new if to_new else old).replace("{i}", match.group(1) if match.groups() else "")
    return key


def _rename_keys(tree: Any, to_new: bool) -> Any:
    """`tree` (dicts, named tuples such as optax states, tuples, lists; other values are
    leaves) with its dict keys renamed by `LEGACY_KEYS`, old -> new (`to_new`) or back."""
    def walk(node, parent):
        if isinstance(node, dict):
            return {_renamed(k, parent, to_new): walk(v, k) for k, v in node.items()}
        if isinstance(node, tuple) and hasattr(node, "_fields"):
            return type(node)(*(walk(getattr(node, f), f) for f in node._fields))
        if isinstance(node, (tuple, list)):
            return type(node)(walk(v, parent) for v in node)
        return node

    return walk(tree, None)


def to_legacy(tree: Any) -> Any:
    """`tree` (e.g. a restore template) with its keys under their old names."""
    return _rename_keys(tree, to_new=False)


def from_legacy(tree: Any) -> Any:
    """`tree` (e.g. restored under the old names) with its keys under the new names."""
    return _rename_keys(tree, to_new=True)


def has_legacy_keys(tree: Any) -> bool:
    """Whether a stored item's tree (its orbax metadata: nested dicts and lists) has a key of
    `LEGACY_KEYS` under its old name."""
    def walk(node, parent):
        if isinstance(node, dict):
            return any(_renamed(k, parent, True) != k or walk(v, k) for k, v in node.items())
        if isinstance(node, (tuple, list)):
            return any(walk(v, parent) for v in node)
        return False

    return walk(tree, None)
