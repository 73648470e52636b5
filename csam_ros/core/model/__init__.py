"""The model: SE(2), the sensor and motion models, the recorded logs, rendezvous rows and settings.
Imports nothing else of the core."""
