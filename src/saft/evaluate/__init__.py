"""saft.evaluate"""
