"""saft.appearance"""
