"""acoustlab plugins, grouped by kind; each is registered by a YAML file in conf/<group>/.

The top-level name ``plugins`` is what the design fixes; another installed project could ship a
package of the same name. ``acoustlab.run.registry.check_plugins_package`` looks for the
marker below before any plugin is built and stops with a clear message when it is missing.
"""

#: Marks this package as acoustlab's own ``plugins`` (checked by the registry).
ACOUSTLAB_PLUGINS = True
