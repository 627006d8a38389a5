"""The seeder controller, composed from the drivers: one package per domain.

Layers, lowest first (enforced by the import-linter contracts in pyproject.toml):
``protocol`` <- ``drivers`` <- ``gateway.core`` / ``gateway.config`` <- the domains
(``control``, ``metering``, ``recording``, ``calibration``) <- ``state`` (the typed
``MachineState`` the views and the state payload read) <- ``link`` / ``ui`` <- ``app``.
A package imports only from the layers below it; the domains do not import each other.
"""
