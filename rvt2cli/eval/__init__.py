"""rvt2cli.eval"""
