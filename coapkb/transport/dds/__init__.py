"""DDS (Cyclone DDS) transport: :mod:`.transport`; how an endpoint becomes a Cyclone domain: :mod:`.config`."""
