"""Perception: RGB-D observation -> 2D detections. Choose an implementation by name."""

from __future__ import annotations

from tidee.agent.perception.base import Detection, Perception

PERCEPTIONS = ("oracle", "learned")


def make_perception(name: str) -> Perception:
    if name == "oracle":
        from tidee.agent.perception.oracle import OraclePerception

        return OraclePerception()
    if name == "learned":
        from tidee.agent.perception.learned import LearnedPerception

        return LearnedPerception.load()
    raise ValueError(f"unknown perception {name!r}; choose one of {PERCEPTIONS}")


__all__ = ["Detection", "Perception", "PERCEPTIONS", "make_perception"]
