"""rvt2cli.record"""
