"""The control center: a web server for accounts, devices, sessions, live monitoring and episodes.

- :mod:`~telerig.server.accounts`: users with roles, login sessions and the audit log.
- :mod:`~telerig.server.auth`: session cookies, CSRF, role checks, login rate limiting.
- :mod:`~telerig.server.app`: the FastAPI application and its pages.
"""
