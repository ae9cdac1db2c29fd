"""Weather beyond fog: rain, snowfall and night, each a pure function of arrays and its own seeded
stream (derivations: docs/weather.md)."""
