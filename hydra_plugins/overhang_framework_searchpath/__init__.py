"""Hydra search-path plugin: adds every config directory that overhang-framework plugins contribute."""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class OverhangFrameworkSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        from overhang_framework.config import CONFIG_PATH
        from overhang_framework.plugins import config_search_paths

        if not any(e.path == CONFIG_PATH for e in search_path.get_path()):
            return  # another Hydra application
        for path in config_search_paths():
            search_path.append(provider="overhang_framework", path=path)
