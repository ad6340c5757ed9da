"""The science commands of ``ttl``: simulate, info, analyze, diagnose, scenarios."""

__all__ = ["analyze", "diagnose", "info", "main", "progress", "report", "simulate"]
