"""An example method and dataset converter that live outside ``nvs/`` (docs/extending.md)."""
