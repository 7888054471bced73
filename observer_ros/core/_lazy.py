# observer_ros.core._lazy: python-control, imported when first used.
"""
``control``: python-control, imported on first attribute access.

Importing python-control pulls in scipy.signal, scipy.stats and matplotlib.pyplot: about
1 s of a tool's start-up here (2.4 s under load), while the offline tools replaying a
bag with a vehicle's gains often never call it (benchmarks/README.md, P3). The core's
modules use ``control.place`` and the others through this object; the first use imports
the module, every later one is an attribute lookup.

"""

__all__ = ['control']


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
