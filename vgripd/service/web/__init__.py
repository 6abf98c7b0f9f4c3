"""The operator web view, its JSON API and Prometheus metrics (docs/web.md); the server is
``vgripd.service.web.app.WebServer``.

Nothing is imported here: the web view's image helper process imports
``vgripd.service.web.images`` alone, without the server and its HTTP stack.
"""
