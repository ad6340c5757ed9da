"""The science commands of ``ttl``: simulate, info, analyze, diagnose, scenarios.
"""

__all__ = ['diagnose', 'main', 'progress']
