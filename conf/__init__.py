# The package config: loading it registers the config groups' schemas (monostixels/config_schema.py).
import monostixels.config_schema  # noqa: F401
