"""Region and learning configs (TOML) as validated objects."""

from common.exports import lazy_exports

_EXPORTS = {
    "ConfigError": "region",
    "ConfigWarning": "region",
    "FeatureSpec": "region",
    "RegionConfig": "region",
    "load_config": "region",
    "parse_config": "region",
    "utm_crs": "region",
    "LearnConfig": "learn",
    "load_learn_config": "learn",
    "parse_learn": "learn",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
