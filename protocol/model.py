"""The base of every protocol model: frozen, strict about unknown fields, and comparable
when it holds numpy arrays."""

from __future__ import annotations

from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict

M = TypeVar("M", bound=BaseModel)


def first_duplicate(items: tuple[Any, ...] | list[Any]) -> Any:
    """The first item that appears a second time, or None."""
    if len(set(items)) == len(items):  # the common case, in one C call
        return None
    seen: set[Any] = set()
    for item in items:
        if item in seen:
            return item
        seen.add(item)
    return None


class Model(BaseModel):
    """A frozen pydantic model that refuses unknown fields and may hold numpy arrays."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)

    def __eq__(self, other: object) -> bool:
        # pydantic's own __eq__ would ask numpy for the truth value of an array
        if type(other) is not type(self):
            return NotImplemented
        return all(same(getattr(self, name), getattr(other, name))
                   for name in type(self).model_fields)

    __hash__ = None  # type: ignore[assignment]  # arrays are unhashable anyway


def same(a: Any, b: Any) -> bool:
    """Equality that compares numpy arrays by value."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.array_equal(a, b))
    return bool(a == b)


def construct_whole(cls: type[M], values: dict[str, Any]) -> M:
    """``cls.model_construct(**values)`` for a decoder's hot path, where ``values`` holds
    every field, already checked: pydantic's walks each field's aliases and defaults,
    ~10 us for an AvatarBatch, which every spectator builds ~200 times a second. A model
    with a post-init hook, or values that are not exactly its fields, go the long way."""
    if cls.__pydantic_post_init__ or values.keys() != cls.__pydantic_fields__.keys():
        return cls.model_construct(**values)
    model = cls.__new__(cls)
    object.__setattr__(model, "__dict__", values)
    object.__setattr__(model, "__pydantic_fields_set__", set(values))
    object.__setattr__(model, "__pydantic_extra__", None)
    object.__setattr__(model, "__pydantic_private__", None)
    return model
