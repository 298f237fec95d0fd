"""rvt2cli.model"""
