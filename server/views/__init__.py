"""Read models out of the core: KPIs, the live device feed, the camera's set-up view."""
