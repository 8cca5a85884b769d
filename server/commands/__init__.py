"""The command catalogue every transport serves: each command declared once.

`catalogue` names each command (its event, role, request model, payload builder,
operationId, audit wording, whether it is a stop); `answers` turns the worker's
`Outcome` into the status, body and audit label every door gives; `requests`
holds the request and answer models. HTTP (server/api/commands.py), MQTT
(server/mqtt/commands.py), OPC UA (server/opcua/methods.py), the access policy
(server/security/policy.py) and the docs read them; none re-derives a command.
"""
