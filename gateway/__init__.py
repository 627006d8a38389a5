"""Composition of drivers into the seeder controller: config, control, records, MQTT, CLI."""
