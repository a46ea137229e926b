"""The one error type the service raises for client mistakes: an HTTP status + message."""

from __future__ import annotations


class ApiError(Exception):
    def __init__(self, status: int, message: str, details: dict | None = None):
        super().__init__(message)
        self.status = status
        self.message = message
        self.details = details or {}

    def to_dict(self) -> dict:
        d = {"status": self.status, "message": self.message}
        if self.details:
            d["details"] = self.details
        return {"error": d}
