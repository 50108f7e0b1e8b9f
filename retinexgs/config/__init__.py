"""The config at the bottom of the layers: the typed schema (:mod:`retinexgs.config.schema`), configs as plain
data (:mod:`retinexgs.config.files`) and the run format with its migrations (:mod:`retinexgs.config.versions`).

Every layer above imports its section types from here at runtime. Loading a config (the merge of files and
overrides, then the schema and the checks that need the registries above: strategies, the schedule) is
:func:`retinexgs.run.config.load_config`'s."""
from retinexgs.config.files import (RawConfig, configs_dir, merge, parse_override, plain, read_yaml,
                                    resolve_config_path)
from retinexgs.config.schema import Config, ConfigSchema, Section
from retinexgs.config.versions import FORMAT, migrate_checkpoint, migrate_config

__all__ = ["Config", "ConfigSchema", "Section", "RawConfig", "configs_dir", "merge", "parse_override", "plain",
           "read_yaml", "resolve_config_path", "FORMAT", "migrate_checkpoint", "migrate_config"]
