"""identify: fitting flexdyn models to measured joint and tip-deflection logs.

Planned (see the project's identification and discrepancy issues); nothing is
exported yet.
"""
