"""What every group of settings shares: :class:`Section` (unknown keys are errors, also in
``model_copy``) and :func:`lift_flat`, which reads a group's settings given at the level above
it, as config files did before the groups. Imports pydantic only."""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, model_validator


class Section(BaseModel):
    """A group of settings: unknown keys are errors, in a config file and in ``model_copy``
    (whose ``update`` pydantic would otherwise take without a check, leaving a setting given
    at its old place silently unused)."""

    model_config = ConfigDict(extra="forbid")

    def model_copy(self, *, update: dict[str, Any] | None = None, deep: bool = False):
        unknown = set(update or ()) - set(type(self).model_fields)
        if unknown:
            raise TypeError(f"{type(self).__name__} has no setting {', '.join(sorted(unknown))}")
        return super().model_copy(update=update, deep=deep)


def lift_flat(data: Any, groups: dict[str, type[BaseModel]]) -> Any:
    """``data`` (a mapping of settings, or anything else, returned as it is) with every setting
    of a group that is given at the mapping's own level moved into that group's mapping.
    Raises ValueError for a setting given at both places with different values."""
    if not isinstance(data, dict):
        return data
    out = dict(data)
    for name, model in groups.items():
        flat = {k: out.pop(k) for k in list(out) if k in model.model_fields and k not in groups}
        if not flat:
            continue
        group = out.get(name, {})
        group = group.model_dump() if isinstance(group, BaseModel) else dict(group or {})
        for k, v in flat.items():
            if k in group and group[k] != v:
                raise ValueError(f"{k} is given twice, as {v!r} and as {name}.{k} "
                                 f"{group[k]!r}; give it once")
            group[k] = v
        out[name] = group
    return out


class Grouped(Section):
    """A stage's settings with groups of expert settings: ``GROUPS`` (a group's field name ->
    its :class:`Section`); a config may give a grouped setting in its group or, as before the
    groups, at the stage's level (:func:`lift_flat`)."""

    GROUPS: ClassVar[dict[str, type[Section]]] = {}

    @model_validator(mode="before")
    @classmethod
    def _lift(cls, data: Any) -> Any:
        return lift_flat(data, cls.GROUPS)

    def flat_dump(self) -> dict[str, Any]:
        """Every setting by its name, the groups' lifted to the top: the settings as they were
        before the groups (a fingerprint of them stays the same)."""
        data = self.model_dump()
        for name in self.GROUPS:
            data |= data.pop(name)
        return data

    def replaced(self, **settings: Any):
        """This config with ``settings`` changed, each by its name whether it sits at the top
        or in a group, validated as a config file's are. TypeError for an unknown name."""
        data = self.model_dump()
        for name, value in settings.items():
            group = next((g for g, model in self.GROUPS.items() if name in model.model_fields),
                         None)
            if group is None and name not in type(self).model_fields:
                raise TypeError(f"{type(self).__name__} has no setting {name}")
            (data[group] if group else data)[name] = value
        return type(self).model_validate(data)
