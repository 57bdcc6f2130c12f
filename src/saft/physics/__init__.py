"""saft.physics"""
