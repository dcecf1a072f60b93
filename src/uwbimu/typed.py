"""Typed results that still read like the dictionaries they replace.

A result class is a dataclass whose main quantities are typed fields (documented with units)
and whose remaining, analysis-specific keys live in ``extra``.  It is also a read-only
:class:`collections.abc.Mapping` over all of them, so code written for the former plain
dictionaries keeps working (``r["rank"]``, ``r.get("name")``, ``dict(r)``, ``**r``), while
new code writes ``r.rank``.  :meth:`MappingResult.to_dict` gives the plain dictionary
(for YAML / JSON).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Iterator, TypeVar

T = TypeVar("T", bound="MappingResult")


class MappingResult(Mapping):
    """Mixin for a ``@dataclass(eq=False)`` with a field ``extra: dict``: mapping access over fields and extras.

    Built with :meth:`from_dict`, the mapping has exactly the keys of that dictionary, in its
    order (a field the dictionary lacked reads as its default but is not a key); built
    directly, every field is a key.  Equality is the mapping's (a result equals the
    dictionary it was built from).
    """

    _order: "list[str] | None" = None  # keys in their original order (set by from_dict)

    def _field_names(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self) if f.name != "extra"]

    def _keys(self) -> list[str]:
        if self._order is not None:
            return self._order
        return self._field_names() + list(self.extra)

    def __getitem__(self, key: str) -> Any:
        if key not in self._keys():
            raise KeyError(key)
        if key in self._field_names():
            return getattr(self, key)
        return self.extra[key]

    def __setitem__(self, key: str, value: Any) -> None:
        if key in self._field_names():
            setattr(self, key, value)
        else:
            self.extra[key] = value
        if self._order is not None and key not in self._order:
            self._order.append(key)

    def __contains__(self, key: object) -> bool:
        return key in self._keys()

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._keys()))

    def __len__(self) -> int:
        return len(self._keys())

    def to_dict(self) -> dict[str, Any]:
        """The plain dictionary (keys in their original order, values as stored)."""
        return {k: self[k] for k in self}

    def copy(self) -> dict[str, Any]:
        """A plain shallow copy (as ``dict.copy`` gave)."""
        return self.to_dict()

    @classmethod
    def from_dict(cls: type[T], data: Mapping[str, Any]) -> T:
        """Build from a mapping: known keys fill the fields, the others go to ``extra``."""
        names = {f.name for f in dataclasses.fields(cls) if f.name != "extra"}
        obj = cls(**{k: v for k, v in data.items() if k in names},
                  extra={k: v for k, v in data.items() if k not in names})
        obj._order = list(data)
        return obj

    __hash__ = None  # mutable, like the dict it replaces
