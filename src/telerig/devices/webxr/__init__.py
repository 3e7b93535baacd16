"""WebXR headset / phone input: a telerig-served page streams head, controllers and hands over a WebSocket."""

__all__: list[str] = []
