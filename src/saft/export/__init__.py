"""saft.export"""
