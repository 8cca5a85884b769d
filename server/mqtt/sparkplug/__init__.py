"""The cell as a Sparkplug B edge node on the plant's broker (docs/plant-integration.md).

Off unless `sparkplug_group` is set; a connection of its own beside the MQTT link.
"""
