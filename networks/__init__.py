"""Flax modules only: the thesis's actor-critic (SU, NavRL) and GuideRL networks."""

from networks.actor_critic import (
    LOG_STD_RANGE,
    ActorCritic,
    GuideActorCritic,
    GuidePolicy,
    LidarEncoder,
    Outputs,
    count,
    make_inference_fn,
    policy_count,
    transfer_guide_inputs,
    transfer_inputs,
)

_CLASSES = {"ActorCritic": ActorCritic, "GuideActorCritic": GuideActorCritic}


def from_spec(spec: dict):
    """A module from ``{"class": name, **fields}`` (what exported policies record)."""
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in spec.items() if k != "class"}
    if spec.get("class") not in _CLASSES:
        raise ValueError(f"unknown network class {spec.get('class')!r}; known: {sorted(_CLASSES)}")
    return _CLASSES[spec["class"]](**fields)


__all__ = [
    "LOG_STD_RANGE",
    "ActorCritic",
    "GuideActorCritic",
    "GuidePolicy",
    "LidarEncoder",
    "Outputs",
    "count",
    "from_spec",
    "make_inference_fn",
    "policy_count",
    "transfer_guide_inputs",
    "transfer_inputs",
]
