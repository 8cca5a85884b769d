"""Notifications to the plant: webhooks (a signed POST per fault, alert, state change or
completed run), delivered off the worker's path with retries, every outcome journaled.

- `signing`: the HMAC-SHA256 signature of a delivery (timestamp included);
- `notices`: what the cell tells a webhook, built from bus messages and run ends;
- `retry`: which answers are retried, and after how long;
- `deliverer`: one webhook's bounded queue and its delivery task;
- `notifier`: the bus subscriber that feeds every webhook's queue.

A webhook's configuration is a setting (`server/settings/webhooks.py`); where a webhook
may post is a security policy (`server/security/destinations.py`).
"""
