"""rvt2cli.export"""
