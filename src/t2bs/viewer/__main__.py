from t2bs.viewer.commands import main

main()
