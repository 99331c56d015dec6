"""acoustlab plugins, grouped by kind; each is registered by a YAML file in conf/<group>/."""
