"""Paper C's seed position recording: from a seed-tube edge to a stored, published record.

- ``positioning``: GNSS epochs + edge times -> where each seed landed;
- ``recorder``: the seed path (queue, position, store) run in bursts;
- ``seed_plausibility``: edges faster than a meter can drop are counted, not stored;
- ``spacing_quality``: ISO 7256-1 per-row quality (multiples, misses, precision);
- ``store`` and ``id_ranges``: the durable SQLite record store and its delivered-id ranges;
- ``health``: the recording alarms (GNSS, sensors, store);
- ``export``: GeoJSON/CSV exports; ``gnss_diagnostics``: ``sowgate decode-gnss``;
- ``field_stats``: the field report's streamed sums and map (``sowgate report`` draws them).
"""

__all__ = [
    "export",
    "field_stats",
    "gnss_diagnostics",
    "health",
    "id_ranges",
    "positioning",
    "recorder",
    "seed_plausibility",
    "spacing_quality",
    "store",
]
