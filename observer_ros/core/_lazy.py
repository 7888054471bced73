# observer_ros.core._lazy: python-control and the packages' names, imported when first used.
"""
``control``: python-control, imported on first attribute access.

Importing python-control pulls in scipy.signal, scipy.stats and matplotlib.pyplot: about
1 s of a tool's start-up here (2.4 s under load), while the offline tools replaying a
bag with a vehicle's gains often never call it (benchmarks/README.md, P3). The core's
modules use ``control.place`` and the others through this object; the first use imports
the module, every later one is an attribute lookup.

"""

__all__ = ['control', 'exports']

import importlib


class _LazyModule:
    """A module imported by ``load()`` on the first attribute access."""

    def __init__(self, name, load):
        self._name = name
        self._load = load
        self._module = None

    def __getattr__(self, attr):
        module = self._module
        if module is None:
            module = self._module = self._load()
        return getattr(module, attr)

    def __repr__(self):
        state = 'imported' if self._module is not None else 'not imported yet'
        return f'<lazily imported module {self._name!r} ({state})>'


def _import_control():
    import control      # a plain import statement: the package.xml check sees it
    return control


control = _LazyModule('control', _import_control)


def exports(package, names_by_module):
    """
    Return a package's ``__all__``, ``__getattr__`` and ``__dir__`` for names imported lazily.

    ``names_by_module`` maps each submodule to the names it exports. A name is taken from
    its submodule when first asked for (``from package import name``, ``import *``,
    ``package.name``), the submodule imported then; an attribute that is a submodule's name
    imports that submodule. A package's ``__init__`` so costs nothing until it is used.

    Parameters
    ----------
    package : dict
        The package's ``globals()``; a name, once imported, is kept there.
    names_by_module : dict
        Submodule name (relative) -> tuple of the names it exports.

    """
    name = package['__name__']
    source = {attr: module for module, attrs in names_by_module.items() for attr in attrs}

    def __getattr__(attr):
        module = source.get(attr)
        if module is not None:
            value = getattr(importlib.import_module(f'{name}.{module}'), attr)
            package[attr] = value
            return value
        if not attr.startswith('_'):
            try:
                return importlib.import_module(f'{name}.{attr}')
            except ModuleNotFoundError as err:
                if err.name != f'{name}.{attr}':
                    raise
        raise AttributeError(f'module {name!r} has no attribute {attr!r}')

    all_names = [attr for attrs in names_by_module.values() for attr in attrs]

    def __dir__():
        return sorted(set(package) | set(all_names))

    return all_names, __getattr__, __dir__
