import pstats, io
s=io.StringIO(); st=pstats.Stats('/tmp/p.prof',stream=s); st.sort_stats('cumulative').print_stats('topocut|pipelines',40); print(s.getvalue()[-9000:])
