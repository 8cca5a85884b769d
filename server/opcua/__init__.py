"""The cell on OPC UA: PackML tags, its own state and its commands (docs/plant-integration.md).

One more bus subscriber and one more command source, on the same command path
and roles as HTTP. Off unless `opcua_endpoint` is set.
"""
