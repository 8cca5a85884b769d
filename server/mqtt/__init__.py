"""The cell's MQTT side: one more bus subscriber, and optionally one more command door.

`topics.py` names the topics and builds each message (pure), `outbox.py` holds
what is waiting for the broker (bounded), `link.py` keeps the connection and
publishes, `commands.py` runs a command received over MQTT through the same
path and roles as HTTP, once `signed.py` has checked its signature, age and
nonce. See docs/plant-integration.md for the topic contract.
"""
