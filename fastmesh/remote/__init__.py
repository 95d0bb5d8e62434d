"""The service seen from outside: the HTTP client (``client``) and the load tester that drives it (``loadtest``)."""
