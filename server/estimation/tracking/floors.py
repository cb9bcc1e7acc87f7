"""Floor selection with hysteresis.

The session's floor changes to the fingerprint model's floor only after
``required`` consecutive fixes agree on the same other floor; one stray fix on
another floor does nothing.
"""

from __future__ import annotations

from typing import Any


class FloorTracker:
    def __init__(self, floor: int, required: int = 3):
        if required < 1:
            raise ValueError("required must be >= 1")
        self.floor = int(floor)
        self.required = int(required)
        self.candidate: int | None = None
        self.count = 0

    def observe(self, fix_floor: int) -> bool:
        """Feed the floor of one fix; returns True when the floor changed now."""
        fix_floor = int(fix_floor)
        if fix_floor == self.floor:
            self.candidate, self.count = None, 0
            return False
        if fix_floor == self.candidate:
            self.count += 1
        else:
            self.candidate, self.count = fix_floor, 1
        if self.count >= self.required:
            self.floor = fix_floor
            self.candidate, self.count = None, 0
            return True
        return False

    def to_dict(self) -> dict[str, Any]:
        return {"floor": self.floor, "required": self.required, "candidate": self.candidate, "count": self.count}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FloorTracker:
        obj = cls(data["floor"], data["required"])
        obj.candidate = data["candidate"]
        obj.count = int(data["count"])
        return obj
