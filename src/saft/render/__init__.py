"""saft.render"""
