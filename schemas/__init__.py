"""Message schemas of the rvt2 episode format; shipped inside the package as `rvt2cli._schemas`."""
